"""The registered stream ops (torch.ops.lidarops.pillar_stream_push / _gather) with corrupted state:
a clear error or a reported corruption, never an out-of-bounds access.

Values of the state tensors are checked where the kernels read them (docs/stream.md, "Design",
and docs/notes/sscater.md): the push reports a bad value in stats[4] (a kPsBad* bit) and changes nothing;
the gather reports -1 points for a pillar whose slot, head or count is out of range; shapes, dtypes,
devices and the scalar arguments raise ValueError at entry. PillarStream turns the reports into a
RuntimeError naming the tensor and the value.

A regression here would be a segfault, so the cases run in one child process per device (this file,
run as a script) that prints one JSON line per case; a crash fails the cases it did not reach.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from helpers.devices import DEVICES

# stats[4] bits (csrc/include/lidarops/pillar_stream.h)
BAD_RUNS, BAD_LOG, BAD_CELL_SLOT, BAD_QUEUE, BAD_NUM_FREE, BAD_FREE_SLOTS = 4, 8, 16, 32, 64, 128
N, M = 4, 6
STATE = ("pool_xyzi", "pool_t", "head", "count", "slot_cell", "cell_slot", "free_slots", "num_free", "log_cell",
         "log_t")

# ---- the cases (run in the child) ----
# A stream on a 4 x 4 grid holds 3 points in pillar A (key 0) and 1 in pillar B (key 5) at t = 0; the
# raw push at t = 0.2 expires all of them and brings 2 points to A and one each to the new pillars C
# (key 10) and D (key 15): B's slot is freed and popped again, and D pops an older entry of the free
# stack. So the push reads every kind of state value: runs, the log, cell_slot, slot_cell, head,
# count, the free stack and num_free.
KEY_A, KEY_B, KEY_C = 0, 5, 10

# name -> (how to corrupt the state tensors `s` (a dict) or the call's arguments `a`, expected outcome)
PUSH_CASES = {
    "count > N": ("s['count'][slot(s, KEY_A)] = N + 5", ("flag", BAD_QUEUE)),
    "count < 0": ("s['count'][slot(s, KEY_A)] = -3", ("flag", BAD_QUEUE)),
    "head >= N": ("s['head'][slot(s, KEY_A)] = N", ("flag", BAD_QUEUE)),
    "head < 0": ("s['head'][slot(s, KEY_B)] = -1", ("flag", BAD_QUEUE)),
    "count < expiries": ("s['count'][slot(s, KEY_A)] = 1", ("flag", BAD_QUEUE)),
    "cell_slot >= M": ("s['cell_slot'][KEY_A] = M + 3", ("flag", BAD_CELL_SLOT)),
    "cell_slot < -1": ("s['cell_slot'][KEY_B] = -5", ("flag", BAD_CELL_SLOT)),
    "cell_slot huge": ("s['cell_slot'][KEY_A] = 2**31 - 1", ("flag", BAD_CELL_SLOT)),
    "slot_cell out of range": ("s['slot_cell'][slot(s, KEY_A)] = 10**6", ("flag", BAD_CELL_SLOT)),
    "slot_cell of another pillar": ("s['slot_cell'][slot(s, KEY_A)] = KEY_B", ("flag", BAD_CELL_SLOT)),
    "free_slots out of range": ("s['free_slots'][:] = 1000", ("flag", BAD_FREE_SLOTS)),
    "free_slots negative": ("s['free_slots'][:] = -7", ("flag", BAD_FREE_SLOTS)),
    "free_slots in use": ("s['free_slots'][:] = slot(s, KEY_A)", ("flag", BAD_FREE_SLOTS)),
    "num_free > M": ("s['num_free'][0] = M + 1", ("flag", BAD_NUM_FREE)),
    "num_free < 0": ("s['num_free'][0] = -1", ("flag", BAD_NUM_FREE)),
    "num_free leaves no room for frees": ("s['num_free'][0] = M", ("flag", BAD_NUM_FREE)),
    "log_cell out of range": ("s['log_cell'][0] = 16 + 7", ("flag", BAD_LOG)),
    "log_cell negative": ("s['log_cell'][1] = -2", ("flag", BAD_LOG)),
    "log_cell of an empty pillar": ("s['log_cell'][0] = KEY_C", ("flag", BAD_LOG)),
    "run start > end": ("a['runs'] = torch.tensor([[3, 1]])", ("flag", BAD_RUNS)),
    "run start < 0": ("a['runs'] = torch.tensor([[-2, 2]])", ("flag", BAD_RUNS)),
    "run longer than the log": ("a['runs'] = torch.tensor([[0, s['log_cell'].numel() + 1]])", ("flag", BAD_RUNS)),
    "run near 2^63": ("a['runs'] = torch.tensor([[2**63 - 5, 2**63 - 1]])", ("flag", BAD_LOG)),
    "log_head < 0": ("a['log_head'] = -1", ("value_error", r"log_head must be in \[0, 2\^62\), got -1")),
    "log_head huge": ("a['log_head'] = 2**62", ("value_error", "log_head must be in")),
    "cutoff NaN": ("a['cutoff'] = float('nan')", ("value_error", "cutoff must not be NaN")),
    "head wrong size": ("s['head'] = s['head'][:-1].clone()", ("value_error", r"int32 \(M,\) with M = 6")),
    "count wrong dtype": ("s['count'] = s['count'].long()", ("value_error", "int32")),
    "cell_slot wrong size": ("s['cell_slot'] = s['cell_slot'][:-1].clone()", ("value_error", r"cell_slot must be int32 \(H \* W,\)")),
    "num_free wrong size": ("s['num_free'] = torch.zeros(2, dtype=torch.int32, device=dev)", ("value_error", r"num_free must be int32 \(1,\)")),
    "log_t length differs": ("s['log_t'] = s['log_t'][:-1].clone()", ("value_error", "one length L")),
    "pool_t wrong dtype": ("s['pool_t'] = s['pool_t'].float()", ("value_error", "pool_t must be float64")),
    "pool_t wrong shape": ("s['pool_t'] = s['pool_t'][:, :-1].clone()", ("value_error", r"pool_t must be float64 \(M, N\)")),
    "state not contiguous": ("s['count'] = torch.zeros(2 * M, dtype=torch.int32, device=dev)[::2]", ("value_error", "count .stream state. must be contiguous")),
    "runs wrong dtype": ("a['runs'] = torch.zeros(1, 2, dtype=torch.int32)", ("value_error", "runs must be int64")),
    "points wrong shape": ("a['points'] = torch.zeros(3, 3)", ("value_error", r"points must be float32 \(n, 4\)")),
    "t length differs": ("a['t'] = torch.zeros(2, dtype=torch.float64)", ("value_error", r"t must be float64 \(n,\) with n = 4")),
    "more points than the log": ("a['points'] = torch.zeros(5000, 4); a['t'] = torch.zeros(5000, dtype=torch.float64)", ("value_error", "needs a log of at least")),
    "grid_hw wrong": ("a['grid_hw'] = [4, 0]", ("value_error", "grid_hw must be")),
    # scalars (log_head and cutoff read on the device, a CUDA graph's push): shapes raise, values are state
    "scalars wrong dtype": ("a['scalars'] = torch.zeros(2, dtype=torch.int32, device=dev)",
                            ("value_error", r"scalars must be int64 \(2,\)")),
    "scalars wrong shape": ("a['scalars'] = torch.zeros(3, dtype=torch.int64, device=dev)",
                            ("value_error", r"scalars must be int64 \(2,\)")),
    "scalars log_head < 0": ("a['scalars'] = scal(-1, 0.1)", ("flag", BAD_LOG)),
    "scalars log_head huge": ("a['scalars'] = scal(2**62, 0.1)", ("flag", BAD_LOG)),
    "scalars cutoff NaN": ("a['scalars'] = scal(a['log_head'], float('nan'))", ("flag", BAD_LOG)),
    "scalars in place of bad arguments": ("a['scalars'] = scal(a['log_head'], 0.1); a['log_head'] = -1; "
                                          "a['cutoff'] = float('nan')", ("ok", None)),
}

GATHER_CASES = {  # cells = [A, B, C (empty), 99 (outside the grid)]: expected num_points
    "consistent": ("", ("gather", [3, 1, 0, 0])),
    "cell_slot >= M": ("s['cell_slot'][KEY_A] = M + 3", ("gather", [-1, 1, 0, 0])),
    "cell_slot < -1": ("s['cell_slot'][KEY_B] = -9", ("gather", [3, -1, 0, 0])),
    "count > N": ("s['count'][slot(s, KEY_A)] = N + 100", ("gather", [-1, 1, 0, 0])),
    "count < 0": ("s['count'][slot(s, KEY_B)] = -1", ("gather", [3, -1, 0, 0])),
    "head >= N": ("s['head'][slot(s, KEY_A)] = 10**6", ("gather", [-1, 1, 0, 0])),
    "head < 0": ("s['head'][slot(s, KEY_A)] = -7", ("gather", [-1, 1, 0, 0])),
    "head wrong size": ("s['head'] = s['head'][:-1].clone()", ("value_error", r"head and count must be int32 \(M,\)")),
    "cells int32": ("a['cells'] = a['cells'].int()", ("value_error", "cells must be int64")),
    "cell_slot 2-D": ("s['cell_slot'] = s['cell_slot'].view(4, 4)", ("value_error", "cell_slot must be int32")),
    "pool not contiguous": ("s['pool_xyzi'] = torch.zeros(M, N, 8, device=dev)[..., ::2]",
                            ("value_error", r"state \(pool_xyzi, head, count, cell_slot\) must be contiguous")),
}

WRAPPER_CASES = {  # corrupt a PillarStream's private state, then push or read: RuntimeError naming it
    "push: count": ("st._count[int(st._cell_slot[KEY_A])] = 50; push()", ("runtime_error", r"count\[\d\] = 50 is outside \[0, max_points_per_pillar = 4\]")),
    "push: head": ("st._head[int(st._cell_slot[KEY_A])] = -4; push()", ("runtime_error", r"head\[\d\] = -4 is outside \[0, max_points_per_pillar = 4\)")),
    "push: cell_slot": ("st._cell_slot[KEY_A] = 77; push()", ("runtime_error", r"cell_slot\[0\] = 77 is outside \[-1, max_pillars = 6\)")),
    "push: free_slots": ("st._free_slots[:] = 99; push()", ("runtime_error", r"free_slots\[\d\] = 99 is outside")),
    "push: num_free": ("st._num_free[0] = 9; push()", ("runtime_error", r"num_free = 9 is outside \[0, max_pillars = 6\]")),
    "pillars: count": ("st._count[int(st._cell_slot[KEY_A])] = 50; st.pillars()", ("runtime_error", r"count\[\d\] = 50")),
    "pillars: cell_slot": ("st._cell_slot[KEY_B] = 77; st.pillars(torch.tensor([[0, 1, 1]], device=dev))", ("runtime_error", r"cell_slot\[5\] = 77")),
}


def _child(device: str) -> None:
    """Run every case; print one JSON line per case (flushed, so that a crash shows where)."""
    import torch

    from lidarops.stream import PillarGrid, PillarStream

    dev = device
    grid = PillarGrid((0.0, 0.0, -1.0, 4.0, 4.0, 1.0), (1.0, 1.0))
    pts = lambda xy: torch.tensor([[x, y, 0.0, 1.0] for x, y in xy], dtype=torch.float32)  # noqa: E731

    def fresh() -> PillarStream:
        st = PillarStream(grid, window=0.1, max_points_per_pillar=N, max_pillars=M, device=dev)
        st.push(pts([(0.5, 0.5)] * 3 + [(1.5, 1.5)]).to(dev), torch.zeros(4, dtype=torch.float64, device=dev))
        return st

    def state(st):
        return {k: getattr(st, "_" + k).clone() for k in STATE}

    def slot(s, key):
        return int(s["cell_slot"][key])

    def scal(log_head, cutoff):  # the op's scalars: log_head and the bits of cutoff
        bits = torch.tensor([cutoff], dtype=torch.float64).view(torch.int64)
        return torch.cat([torch.tensor([log_head], dtype=torch.int64), bits]).to(dev)

    def run(case: str, code: str, call) -> dict:
        st = fresh()
        s = state(st)
        a = call(st)
        try:
            exec(code, {"s": s, "a": a, "st": st, "torch": torch, "dev": dev, "slot": slot, "N": N, "M": M,
                        "KEY_A": KEY_A, "KEY_B": KEY_B, "KEY_C": KEY_C, "push": a.get("push"), "scal": scal})
            if "op" not in a:
                return {"outcome": "no error"}
            for k in ("runs", "points", "t", "cells"):
                if k in a and isinstance(a[k], torch.Tensor):
                    a[k] = a[k].to(dev)
            before = {k: v.clone() for k, v in s.items()}
            out = a["op"](s, a)
            if a["op_name"] == "gather":
                return {"outcome": "gather", "num_points": out[1].tolist(), "finite": bool(out[0].isfinite().all())}
            unchanged = all(torch.equal(before[k], s[k]) for k in s)
            return {"outcome": "flag", "flags": int(out[1][4]), "unchanged": unchanged}
        except ValueError as e:
            return {"outcome": "value_error", "message": str(e)}
        except RuntimeError as e:
            return {"outcome": "runtime_error", "message": str(e)}

    def push_args(st, drop=False):
        g = grid
        runs = torch.tensor(list(st._runs), dtype=torch.int64).reshape(-1, 2)
        a = {"points": pts([(0.5, 0.5), (0.6, 0.6), (2.5, 2.5), (3.5, 3.5)]),
             "t": torch.full((4,), 0.2, dtype=torch.float64),
             "runs": runs, "log_head": st._log_head, "cutoff": 0.1, "grid_hw": list(g.shape), "op_name": "push"}

        def op(s, a):
            return torch.ops.lidarops.pillar_stream_push(
                *(s[k] for k in STATE), a["points"], a["t"], a["runs"], a["log_head"], a["cutoff"],
                list(g.point_cloud_range), list(g.pillar_size), a["grid_hw"], drop, scalars=a.get("scalars"))
        a["op"] = op
        return a

    def push_drop_args(st):  # the overflow rule's plan reads the same state values
        return push_args(st, drop=True)

    def gather_args(st):
        def op(s, a):
            return torch.ops.lidarops.pillar_stream_gather(s["pool_xyzi"], s["head"], s["count"], s["cell_slot"],
                                                           a["cells"])
        return {"cells": torch.tensor([KEY_A, KEY_B, KEY_C, 99]), "op": op, "op_name": "gather"}

    def wrapper_args(st):
        p, t = pts([(0.5, 0.5), (2.5, 2.5)]).to(dev), torch.full((2,), 0.05, dtype=torch.float64, device=dev)
        return {"push": lambda: st.push(p, t)}

    for table, call in ((PUSH_CASES, push_args), (PUSH_CASES, push_drop_args), (GATHER_CASES, gather_args),
                        (WRAPPER_CASES, wrapper_args)):
        for case, (code, _) in table.items():
            print(json.dumps({"case": f"{call.__name__}:{case}", **run(case, code, call)}), flush=True)
    print(json.dumps({"case": "done"}), flush=True)


# ---- the tests (parent) ----

_RESULTS: dict = {}


def _results(device: str) -> tuple[dict, str]:
    if device not in _RESULTS:
        tests = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # for helpers
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")]))
        r = subprocess.run([sys.executable, __file__, device], capture_output=True, text=True, timeout=600, env=env)
        lines = [json.loads(x) for x in r.stdout.splitlines() if x.startswith("{")]
        tail = f"child exit code {r.returncode}; stderr: {r.stderr[-2000:]}"
        _RESULTS[device] = ({x["case"]: x for x in lines}, tail)
    return _RESULTS[device]


def _check(device: str, name: str, expected) -> None:
    results, tail = _results(device)
    assert name in results, f"{name}: no result: the child process died before or in this case ({tail})"
    got = results[name]
    kind, want = expected
    if kind == "ok":  # the push ran: no flag, and it changed the state
        assert got["outcome"] == "flag" and got["flags"] == 0 and not got["unchanged"], f"{name}: {got}"
    elif kind == "flag":
        assert got["outcome"] == "flag", f"{name}: {got}"
        assert got["flags"] & want, f"{name}: expected bit {want} in stats[4], got {got['flags']}"
        assert got["unchanged"], f"{name}: the push changed the state although it reported corruption"
    elif kind == "gather":
        assert got["outcome"] == "gather" and got["num_points"] == want and got["finite"], f"{name}: {got}"
    else:
        import re
        assert got["outcome"] == kind, f"{name}: expected {kind} matching {want!r}, got {got}"
        assert re.search(want, got["message"]), f"{name}: {got['message']!r} does not match {want!r}"


def _params(table: dict, prefix: str):
    return [pytest.param(f"{prefix}:{name}", exp, id=f"{prefix}:{name}") for name, (_, exp) in table.items()]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name, expected", _params(PUSH_CASES, "push_args") + _params(PUSH_CASES, "push_drop_args"))
def test_push_with_corrupt_state(device, name, expected):
    _check(device, name, expected)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name, expected", _params(GATHER_CASES, "gather_args"))
def test_gather_with_corrupt_state(device, name, expected):
    _check(device, name, expected)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name, expected", _params(WRAPPER_CASES, "wrapper_args"))
def test_stream_reports_corrupt_state(device, name, expected):
    _check(device, name, expected)


@pytest.mark.parametrize("device", DEVICES)
def test_child_ran_every_case(device):
    results, tail = _results(device)
    assert "done" in results, f"the child process did not finish: {tail}"


if __name__ == "__main__":
    _child(sys.argv[1])
