"""Helpers of the command-line tests."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def repo_config(name: str) -> Path:
    """A shipped config by file name, wherever under configs/ it lives."""
    found = sorted((REPO / "configs").rglob(name))
    assert found, f"no {name} under {REPO / 'configs'}"
    return found[0]


def one_error_line(err: str, command: str) -> str:
    """The single line of ``err``, which must read ``lidarops <command>: error: ...`` (no traceback)."""
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), f"expected one line on stderr, got:\n{err}"
    assert lines[0].startswith(f"lidarops {command}: error: "), lines[0]
    assert "Traceback" not in err
    return lines[0]
