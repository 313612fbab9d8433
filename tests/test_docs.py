"""Every code block of README.md, CONTRIBUTING.md, CHANGELOG.md and docs/*.md runs here, so the documentation
cannot rot.

* ```python blocks of a page run in order, in one namespace per page (a page's blocks build on each other),
  in a fresh interpreter, from a temporary folder. Without a GPU, ``device="cuda"`` and ``.cuda()`` become
  their CPU forms: the CPU variant of a GPU example.
* ```bash blocks run line by line (``\\`` continuations joined), with ``lidarops`` and ``python`` this
  checkout's interpreter, in the same temporary folder (``configs/``, ``tools/``, ``benchmarks/`` and
  ``tests/`` linked into it, ``/tmp/`` paths moved into it). ``make`` and ``pip install`` lines are not run
  here: CI runs ``make test`` itself and tests have no network. Long commands are shortened by
  :data:`SHORTER` (fewer frames and epochs; on a CPU, float32 instead of bf16 autocast); the commands and
  their other arguments run as written.
* Other blocks (```text, ```yaml, output without a language) are listings and are not run.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", REPO / "CONTRIBUTING.md", REPO / "CHANGELOG.md"] + sorted((REPO / "docs").glob("*.md"))
SLOW_PAGES = {"README.md", "detector.md", "train.md", "data.md", "sscater.md", "boxes.md", "query.md"}  # pages that simulate or train

#: (regex, replacement) applied to bash lines: the documented runs take minutes to hours
SHORTER = [
    (r"--frames 2400 1200\b", "--frames 6 3"),
    (r"--workers 16\b", "--workers 1"),
    (r"--epochs 30\b", "--epochs 1"),
    (r"--batch-size 8\b", "--batch-size 2"),
    (r"--eval-every 5\b", "--eval-every 1"),
    (r"--seconds [0-9.]+", "--seconds 0.3"),
]
if not torch.cuda.is_available():  # the CPU variant of a GPU example: bf16 autocast is emulated (10x slower) on
    SHORTER.append((r"--amp bf16\b", "--amp none"))  # CPUs without bf16 instructions
if torch.cuda.device_count() <= 1:  # a 2-GPU torchrun example on a machine of one GPU (or none): one process;
    SHORTER.append((r"--nproc_per_node=2\b", "--nproc_per_node=1"))  # tests/train covers DDP with 2 (gloo)

#: optional packages (tools/ensure_env.py): a block that needs a missing one skips, as their tests do
OPTIONAL = ("h5py", "matplotlib", "scipy", "shapely", "pandas", "tqdm", "onnxscript", "onnxruntime", "duckdb",
            "pyarrow")

_FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```\s*$", re.S | re.M)


def code_blocks(page: Path) -> list[tuple[str, int, str]]:
    """(language, line number, source) of each fenced block of a markdown page."""
    text = page.read_text()
    out = []
    for m in _FENCE.finditer(text):
        out.append((m.group(1).lower(), text.count("\n", 0, m.start()) + 2, m.group(2)))
    return out


def _cpu_variant(src: str) -> str:
    if torch.cuda.is_available():
        return src
    return (src.replace('device="cuda"', 'device="cpu"').replace("device='cuda'", "device='cpu'")
            .replace(".cuda()", ""))


def _bash_lines(src: str) -> list[str]:
    lines, cur = [], ""
    for raw in src.splitlines():
        line = raw.rstrip()
        if line.endswith("\\"):
            cur += line[:-1] + " "
            continue
        cur += line
        stripped = cur.split(" #")[0].strip() if not cur.lstrip().startswith("#") else ""
        if stripped and not re.match(r"^(make|pip)\b", stripped):
            lines.append(stripped)
        cur = ""
    return lines


def _workdir(tmp_path: Path) -> dict:
    for name in ("configs", "tools", "benchmarks", "tests"):
        (tmp_path / name).symlink_to(REPO / name)
    shim = tmp_path / ".bin"
    shim.mkdir()
    (shim / "lidarops").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m lidarops "$@"\n')
    (shim / "lidarops").chmod(0o755)
    for name in ("python", "python3"):  # scripts, not symlinks: a venv's python must be run by its own path
        (shim / name).write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
        (shim / name).chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = f"{shim}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = f"{REPO}{os.pathsep}{env.get('PYTHONPATH', '')}".rstrip(os.pathsep)
    env["MPLBACKEND"] = "Agg"
    return env


def _params():
    for page in PAGES:
        marks = [pytest.mark.slow] if page.name in SLOW_PAGES else []
        yield pytest.param(page, id=str(page.relative_to(REPO)), marks=marks)


def _skip_if_optional_missing(error: str, rel, line: int) -> None:
    m = re.search(r"No module named '([\w.]+)'", error)
    if m and m.group(1).split(".")[0] in OPTIONAL:
        pytest.skip(f"{rel}:{line} needs the optional package {m.group(1)}, which is not installed")


_WORKER = r"""
import contextlib, io, json, sys, traceback
sys.path.insert(0, sys.argv[1])
ns = {"__name__": "__doc_page__"}
for request in sys.stdin:
    block = json.loads(request)
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(block["src"], block["name"], "exec"), ns)
        reply = {"ok": True}
    except BaseException:
        reply = {"ok": False, "error": traceback.format_exc()[-3000:], "stdout": out.getvalue()[-1000:]}
    sys.__stdout__.write(json.dumps(reply) + "\n")
    sys.__stdout__.flush()
"""


def _progress(request):
    """A line on the terminal as each block starts: a page can run for minutes, and a silent suite looks hung."""
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    verbose = request.config.getoption("verbose") >= 0 and reporter is not None and capture is not None

    def say(text: str) -> None:
        if verbose:
            with capture.global_and_fixture_disabled():  # past pytest's capture of the test's output
                reporter.write(f"\n    {text} ", flush=True)

    return say


@pytest.mark.parametrize("page", list(_params()))
def test_code_blocks_run(page: Path, tmp_path: Path, request):
    blocks = [b for b in code_blocks(page) if b[0] in ("python", "bash", "sh")]
    if not blocks:
        pytest.skip(f"{page.name} has no python or bash blocks")
    env = _workdir(tmp_path)
    rel = page.relative_to(REPO)
    say = _progress(request)
    # one interpreter per page: its python blocks share a namespace, in page order
    worker = subprocess.Popen([sys.executable, "-c", _WORKER, str(REPO)], cwd=tmp_path, env=env, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        for k, (lang, line, src) in enumerate(blocks, 1):
            say(f"{rel}:{line} ({lang} block {k} of {len(blocks)})")
            src = src.replace("/tmp/", f"{tmp_path}/")
            if lang == "python":
                worker.stdin.write(json.dumps({"src": _cpu_variant(src), "name": f"{rel}:{line}"}) + "\n")
                worker.stdin.flush()
                reply = json.loads(worker.stdout.readline() or '{"ok": false, "error": "the interpreter died"}')
                _skip_if_optional_missing(reply.get("error", ""), rel, line)
                assert reply["ok"], f"{rel}:{line} (python block) failed:\n{reply['error']}"
                continue
            for cmd in _bash_lines(src):
                for pattern, short in SHORTER:
                    cmd = re.sub(pattern, short, cmd)
                proc = subprocess.run(["bash", "-c", cmd], cwd=tmp_path, env=env, capture_output=True, text=True,
                                      timeout=900)
                if proc.returncode:
                    _skip_if_optional_missing(proc.stderr, rel, line)
                assert proc.returncode == 0, (f"{rel}:{line} (bash) `{cmd}` failed with {proc.returncode}:\n"
                                              f"{proc.stdout[-1500:]}\n{proc.stderr[-3000:]}")
    finally:
        worker.stdin.close()
        worker.wait(timeout=60)


def test_fence_parser_finds_blocks():
    page = REPO / "README.md"
    langs = [b[0] for b in code_blocks(page)]
    assert langs.count("python") >= 1 and langs.count("bash") >= 2
    lines = _bash_lines("a \\\n  b  # note\n# only a comment\nmake demo\npip install x\nc")
    assert [" ".join(x.split()) for x in lines] == ["a b", "c"]


def test_index_lists_every_registered_op():
    """CONTRIBUTING.md's op map has one row per op that csrc/ops/*.cpp defines, and no other."""
    defined = set()
    for path in sorted((REPO / "csrc" / "ops").glob("*.cpp")):
        defined |= set(re.findall(r'm\.def\(\s*"(\w+)\(', path.read_text()))
    op_map = (REPO / "CONTRIBUTING.md").read_text().split("## The op map", 1)[1]
    rows = set(re.findall(r"^\| `(\w+)` \|", op_map, re.M))
    assert len(defined) > 30, "the schema pattern stopped matching csrc/ops"
    assert defined == rows, f"missing from CONTRIBUTING.md: {sorted(defined - rows)}; not ops: {sorted(rows - defined)}"


def test_no_message_points_outside_the_repository():
    """Users have the repository, not the developers' workspace: no skip reason, error or doc sends them to
    ../shared or another path above the checkout."""
    root = Path(__file__).resolve().parents[1]
    offenders = []
    for pattern in ("lidarops/**/*.py", "tests/**/*.py", "docs/*.md", "*.md", "Makefile"):
        for path in root.glob(pattern):
            if path.resolve() == Path(__file__).resolve():
                continue
            for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                if "../shared" in line:
                    offenders.append(f"{path.relative_to(root)}:{n}")
    assert not offenders, offenders
