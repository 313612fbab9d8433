"""Fuzz: ``lidarops detect``'s sampler flags (``--sampler``, ``--ratio``, ``--sampler-seed``,
``--sampler-checkpoint``) with hostile values, under test_fuzz_cli's rule: exit code 2 before running, one
line ``lidarops detect: error: ...`` naming the flag or its value as typed, never a traceback, never a file
written. Three valid command lines take the values: without a sampler (where every sampler flag is refused),
behind FPS, and behind a CAS-Net file."""
from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lidarops.cli import main

from .fuzzing import fuzz
from .test_fuzz_cli import _INT_JUNK, _fill, _with

_DETECT = ["detect", "--scenario", "driving_city", "--frames", "1", "--device", "cpu", "--png", "0", "--out", "{out}"]

# a valid command line -> {option: values it must refuse}
BASES: dict[str, tuple[list[str], dict[str, list[str]]]] = {
    "no sampler": (_DETECT, {
        "--ratio": ["8", "1"] + _INT_JUNK,
        "--sampler-seed": ["0", "7"] + _INT_JUNK,
        "--sampler-checkpoint": ["{casnet}", "{missing}"],
    }),
    "fps": (_DETECT + ["--sampler", "fps"], {
        "--sampler": ["voxel", "", "FPS", "cas-net", "casnet "],
        "--ratio": _INT_JUNK + ["0", "-1", "-8"],
        "--sampler-seed": _INT_JUNK + ["-1", str(2**63)],
        "--sampler-checkpoint": ["{casnet}", "{missing}", "{dir}"],
    }),
    "casnet": (_DETECT + ["--sampler", "casnet", "--sampler-checkpoint", "{casnet}"], {
        "--ratio": _INT_JUNK + ["0", "-1"],
        "--sampler-seed": _INT_JUNK + ["-1"],
        "--sampler-checkpoint": ["{missing}", "{dir}", "{binary}", "{empty}", "{detector}", "no_such_shipped_name"],
    }),
}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A CAS-Net file, a checkpoint of a model without one (the shipped detector), junk and missing paths."""
    from lidarops.models import weights
    from lidarops.models.casnet import CASNet

    root = tmp_path_factory.mktemp("detect-sampler-fuzz")
    (root / "binary.bin").write_bytes(bytes(range(256)) * 4)
    (root / "empty.pth").write_bytes(b"")
    (root / "dir").mkdir()
    return {"casnet": CASNet(num_out=16, k=4).save(root / "casnet.pth"), "detector": weights.path(),
            "binary": root / "binary.bin", "empty": root / "empty.pth", "dir": root / "dir",
            "missing": root / "no" / "such.pth"}


@fuzz
@given(data=st.data())
def test_hostile_sampler_flags_are_one_clear_error(tmp_path_factory, files, capsys, data):
    base, hostile = BASES[data.draw(st.sampled_from(sorted(BASES)), "command line")]
    options = data.draw(st.lists(st.sampled_from(sorted(hostile)), min_size=1, max_size=3, unique=True), "options")
    out = tmp_path_factory.mktemp("out")
    paths = {**files, "out": out}
    argv = [_fill(a, paths) for a in base]
    chosen = {}
    for option in options:
        chosen[option] = _fill(data.draw(st.sampled_from(hostile[option]), option), paths)
        argv = _with(argv, option, chosen[option])
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, f"lidarops {' '.join(argv)} exited with {code}, expected 2 (an error)\n{err}"
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("lidarops detect: error: "), \
        f"lidarops {' '.join(argv)}: expected one error line, got:\n{err}"
    named = [o for o in chosen if o in lines[0] or (chosen[o] and chosen[o] in lines[0])]
    assert named, f"lidarops {' '.join(argv)}: the error names none of {sorted(chosen)} nor their values: {lines[0]}"
    assert not any(out.iterdir()), f"lidarops {' '.join(argv)} wrote {sorted(p.name for p in out.iterdir())}"
