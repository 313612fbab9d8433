"""`make build`: compile lidarops._C in place with one line per phase, then install lidarops editable.

The compiler's output goes to build/build.log; the terminal shows how many files are compiled and
about how long that takes, a line at each quarter done, and the time taken, or on failure the
compiler's messages (else the log's last lines) and the log's path. Then lidarops is installed into
the running interpreter's environment (`pip install --no-build-isolation --no-deps --no-index -e .`,
offline; skipped when this checkout is installed already), which compiles nothing: setup.py builds in
the same build/temp.* folder, where ninja finds every object up to date.
Usage: python tools/build.py [--no-install]   (LIDAROPS_NO_INSTALL=1 also skips the install)
"""
from __future__ import annotations

import argparse
import glob
import importlib.metadata
import json
import os
import re
import subprocess
import sys
import sysconfig
import time
from urllib.parse import unquote, urlparse

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LOG = os.path.join("build", "build.log")
INSTALL_LOG = os.path.join("build", "install.log")
TAIL = 25  # log lines shown on failure


def say(msg: str) -> None:
    print(f"[make] {msg}", flush=True)


def usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def plural(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def about(seconds: float) -> str:
    return "under a minute" if seconds < 60 else f"about {max(1, round(seconds / 60))} min"


class Progress:
    """Turns setup.py's and ninja's output into make's lines: the plan, each quarter, the result."""

    def __init__(self):
        self.start = time.monotonic()
        self.cuda = ""
        self.total = None  # files ninja compiles; None until setup.py says
        self.done = 0
        self.quarter = 0

    def feed(self, line: str) -> None:
        m = re.match(r"\[lidarops\] CUDA kernels: (yes|no) \((.*)\); arch list: (.*)", line)
        if m:
            self.cuda = f"C++ and CUDA for {m.group(3)}" if m.group(1) == "yes" else f"C++ only: {m.group(2)}"
            return
        m = re.match(r"\[lidarops\] compiling (\d+) files with (\d+) jobs, about (\d+) s", line)
        if m:
            self.total = int(m.group(1))
            if self.total:
                say(f"compiling {plural(self.total, 'file')} ({self.cuda}; {about(float(m.group(3)))} on "
                    f"{plural(int(m.group(2)), 'core')}; log: {LOG})")
            return
        m = re.match(r"\[(\d+)/(\d+)\] ", line)
        if m:
            self.done, total = int(m.group(1)), int(m.group(2))
            if self.total is None:  # setup.py could not count ahead
                self.total = total
                say(f"compiling {plural(total, 'file')} ({self.cuda}; log: {LOG})")
            quarter = 4 * self.done // total
            if quarter > self.quarter and self.done < total:
                self.quarter = quarter
                say(f"  {self.done}/{total} files compiled ({25 * quarter} %, {self.elapsed():.0f} s)")

    def elapsed(self) -> float:
        return time.monotonic() - self.start


def build(jobs: int) -> int:
    os.makedirs("build", exist_ok=True)
    env = dict(os.environ, MAX_JOBS=str(jobs), PYTHONUNBUFFERED="1")
    # the environment's own commands first: ninja installed by pip into a venv that is not activated
    # (without ninja on PATH torch falls back to compiling one file at a time)
    env["PATH"] = os.pathsep.join([sysconfig.get_path("scripts"), env.get("PATH", "")])
    progress = Progress()
    cmd = [sys.executable, "setup.py", "build_ext", "--inplace"]
    with open(LOG, "w") as log:
        log.write(f"$ MAX_JOBS={jobs} {' '.join(cmd)}\n")
        log.flush()
        with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace",
                              env=env, bufsize=1) as proc:
            for line in proc.stdout:
                log.write(line)
                log.flush()
                progress.feed(line)
        rc = proc.wait()
    took = progress.elapsed()
    if rc != 0:
        fail(rc, took)
        return rc
    if progress.total:
        say(f"built in {took:.0f} s ({plural(progress.total, 'file')} compiled)")
    else:
        say(f"build up to date: nothing to compile ({took:.0f} s)")
    return 0


def fail(rc: int, took: float) -> None:
    """The compiler's messages for the files that failed (ninja's FAILED blocks, without the command
    lines), else the log's last lines; then the log's path."""
    with open(LOG, errors="replace") as f:
        lines = f.read().splitlines()
    shown, inside = [], False
    for ln in lines:
        if ln.startswith("FAILED: "):
            inside = True
            shown.append(ln)
        elif ln.startswith("ninja: build stopped"):
            inside = False
        elif inside and not re.match(r"\S*(c\+\+|g\+\+|gcc|clang\+*|nvcc|cc)\s.* -c ", ln):
            shown.append(ln)
    what = f"compiler messages from {LOG}" if shown else f"last {TAIL} lines of {LOG}"
    shown = shown[:TAIL * 2] if shown else lines[-TAIL:]
    say(f"build FAILED after {took:.0f} s (exit {rc}); {what}:")
    print("\n".join("  " + ln[:400] for ln in shown), flush=True)
    say(f"full log: {os.path.join(ROOT, LOG)}")


def installed_here() -> bool:
    """lidarops is installed editable from this checkout, with its command."""
    try:
        dist = importlib.metadata.distribution("lidarops")
        direct = json.loads(dist.read_text("direct_url.json") or "{}")
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return False
    url = urlparse(direct.get("url", ""))
    same = url.scheme == "file" and os.path.realpath(unquote(url.path)) == os.path.realpath(ROOT)
    # an import-hook install (setuptools' finder, from before setup.py's package_dir) is redone
    hook = any(str(f).endswith("_finder.py") for f in dist.files or [])
    return same and not hook and direct.get("dir_info", {}).get("editable", False) and os.path.exists(script_path())


def script_path() -> str:
    return os.path.join(sysconfig.get_path("scripts"), "lidarops")


def objects_compiled() -> int:
    """Lines of the ninja logs: one per object compiled, ever."""
    total = 0
    for path in glob.glob(os.path.join("build", "temp.*", ".ninja_log")):
        with open(path) as f:
            total += sum(1 for line in f if not line.startswith("#"))
    return total


def install(jobs: int) -> None:
    """Editable install into this interpreter's environment; never fatal (the demo runs from the
    repository root either way)."""
    in_venv = sys.prefix != sys.base_prefix
    if in_venv:
        where = os.path.relpath(sys.prefix) if sys.prefix.startswith(ROOT + os.sep) else sys.prefix
        hint = f"activate it with: source {os.path.join(where, 'bin', 'activate')}"
    else:
        where = f"the environment of {sys.executable}"
        hint = f"the lidarops command is {script_path()}"
    if installed_here():
        say(f"lidarops is installed in {where} (editable, this checkout); {hint}")
        return
    start, before = time.monotonic(), objects_compiled()
    cmd = [sys.executable, "-m", "pip", "install", "--no-build-isolation", "--no-deps", "--no-index", "-e", ROOT]
    with open(INSTALL_LOG, "w") as log:
        log.write(f"$ {' '.join(cmd)}\n")
        log.flush()
        rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, MAX_JOBS=str(jobs)))
    if rc != 0:
        say(f"could not install lidarops into {where} (see {INSTALL_LOG}); it still runs from the repository root")
        return
    again = objects_compiled() - before
    compiled = f"{plural(again, 'file')} recompiled" if again else "nothing recompiled"
    say(f"installed lidarops into {where} (editable, {time.monotonic() - start:.0f} s, {compiled}); {hint}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--no-install", action="store_true", help="build in place only")
    args = parser.parse_args()
    os.chdir(ROOT)
    jobs = int(os.environ.get("MAX_JOBS") or 0) or usable_cpus()
    rc = build(jobs)
    if rc == 0 and not (args.no_install or os.environ.get("LIDAROPS_NO_INSTALL") == "1"):
        install(jobs)
    return rc


if __name__ == "__main__":
    sys.exit(main())
