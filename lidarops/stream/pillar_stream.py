"""Streaming pillarization: a sliding time window of LiDAR points kept as per-pillar queues.

The front end of SSCATeR (sparse convolution with temporal data recycling): points arrive in slices
(e.g. every 10 ms), the window (e.g. 100 ms) slides, and only the pillars whose points changed need
to be recomputed downstream. See ``docs/stream.md``.

Window rule. ``t_newest`` is the largest timestamp seen so far (pushed points, and ``now`` when
given), so it never decreases. After a push the window is ``(t_newest - window, t_newest]``: points
with ``t <= t_newest - window`` leave (or, arriving late, never enter). The stream then holds exactly
the pushed points that are inside the grid and have ``t`` in the window, and ``stream.pillars()``
equals ``pillarize`` of those points (same points per pillar, same decorated features up to float
rounding of the mean; same pillar order, by key ``y * W + x``).

Input policy (``docs/stream.md``, "Input policy"; the same as ``pillarize``'s, defined once in
``lidarops.stream.pillars``): a point whose intensity or timestamp is NaN, infinite or beyond
``MAX_ABS_INTENSITY`` / ``MAX_ABS_TIME`` is dropped and counted (``StreamUpdate.points_invalid``,
``PillarStream.counts``): it never enters the window nor moves ``t_newest``. Non-finite coordinates
are outside the grid (``points_outside``). Bad shapes, dtypes, devices and a bad ``now`` raise
``ValueError``; a capacity overflow raises ``PillarOverflowError`` (``overflow="raise"``) or drops
the points that do not fit by the rule below (``overflow="drop"``); nothing else raises.

Overflow rule (``overflow="drop"``; ``docs/stream.md``, "Overflow policy"). The window is decided
first, from every valid pushed point (a dropped point still moves ``t_newest``), and the points that
leave expire. Then points already in the window are never evicted; the entering points of a pillar
are admitted in (t, arrival) order while its queue has room (``max_points_per_pillar`` minus the
points it keeps); and when more pillars would become occupied than there are free slots
(``max_pillars`` minus the pillars that keep points), the new pillars are admitted in key order
(``y * W + x``) and the entering points of the others are dropped. Dropped points are counted
(``StreamUpdate.points_dropped``, ``PillarStream.counts``).

Cost of a push: proportional to the points entering and leaving the window and the pillars they touch
(plus sorting the entering points, and O(H W) to build the change map and the active list).
"""
from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from lidarops import extension
from lidarops._cuda_graphs import graph_capacity, record_graph, uncached_autocast
from lidarops.ops.validation import describe
from lidarops.ops.voxelize import check_capacity
from lidarops.ops.pillars import (
    MAX_ABS_TIME,
    PillarGrid,
    PillarOverflowError,
    Pillars,
    check_grid,
    decorate_pillars,
    overflow_message,
    without_invalid,
    invalid_points,
)

extension.load()

__all__ = ["PillarStream", "StreamUpdate", "StreamCounts", "MIN_WINDOW"]

#: The shortest window, in seconds: above the float64 resolution of timestamps up to MAX_ABS_TIME (2e-6 s).
MIN_WINDOW = 1e-5

# indices into the stats output of lidarops::pillar_stream_push (csrc/include/lidarops/pillar_stream.h)
(_P_IN, _P_OUT, _P_OUTSIDE, _P_LATE, _P_OVERFLOW, _P_MAX_POINTS, _P_PILLARS, _P_NEW, _P_EMPTIED, _P_TOUCHED,
 _P_SEGMENTS, _P_DROPPED_POINTS, _P_DROPPED_PILLARS, _NUM_STATS) = range(14)
# bits of stats[_P_OVERFLOW]: capacities (kPsOverflow*), and the state checks of the op (kPsBad*)
_OVERFLOW_BITS = 1 | 2
_BAD_RUNS, _BAD_LOG, _BAD_CELL_SLOT, _BAD_QUEUE, _BAD_NUM_FREE, _BAD_FREE_SLOTS = 4, 8, 16, 32, 64, 128


class StreamUpdate(NamedTuple):
    """What one :meth:`PillarStream.push` did.

    Attributes:
        t (float): ``t_newest`` after the push; the window is ``(t - window, t]``.
        active (int32 Tensor[A, 3]): ``(0, y, x)`` of every non-empty pillar, sorted by ``y * W + x``.
        changed (int32 Tensor[C, 3]): pillars that gained or lost at least one point in this push
            (including those that became empty), sorted by key.
        removed (bool Tensor[C]): True where the changed pillar is now empty.
        change_map (bool Tensor[H, W]): True at the changed pillars.
        points_in (int): points that entered the window.
        points_out (int): points that left the window.
        points_outside (int): pushed points outside the grid (never enter).
        points_late (int): pushed points inside the grid but already older than the window (never enter).
        points_invalid (int): pushed points dropped by the input policy: intensity or t NaN, infinite
            or beyond ``MAX_ABS_INTENSITY`` / ``MAX_ABS_TIME`` (never enter).
        points_dropped (int): points that would have entered but did not fit (``overflow="drop"``;
            always 0 with ``overflow="raise"``).

    Each pushed point is counted once, in the first of ``points_invalid``, ``points_outside``,
    ``points_late``, ``points_dropped``, ``points_in``: they add up to the slice's size.
    """

    t: float
    active: Tensor
    changed: Tensor
    removed: Tensor
    change_map: Tensor
    points_in: int
    points_out: int
    points_outside: int
    points_late: int
    points_invalid: int = 0
    points_dropped: int = 0


class StreamCounts(NamedTuple):
    """Cumulative point counts of a :class:`PillarStream` since its creation or :meth:`~PillarStream.reset`
    (pushes that raised are not counted: they had no effect).

    ``points_pushed == points_in + points_outside + points_late + points_invalid + points_dropped``;
    ``points_invalid <= invalid_intensity + invalid_t`` (a point may fail both rules);
    ``points_dropped == dropped_max_points + dropped_max_pillars``.
    """

    points_pushed: int = 0
    points_in: int = 0
    points_out: int = 0
    points_outside: int = 0
    points_late: int = 0
    points_invalid: int = 0
    invalid_intensity: int = 0  # intensity NaN, infinite or |i| > MAX_ABS_INTENSITY
    invalid_t: int = 0  # t NaN, infinite or |t| > MAX_ABS_TIME
    points_dropped: int = 0  # did not fit (overflow="drop")
    dropped_max_points: int = 0  # ... their pillar's queue was full (max_points_per_pillar)
    dropped_max_pillars: int = 0  # ... their pillar was new and no slot was left (max_pillars)


def _as_tensor(x, name: str, device: torch.device) -> Tensor:
    """Tensors must already be on the stream's device; NumPy arrays are copied there."""
    if isinstance(x, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(x)).to(device)
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor or a NumPy array, got {type(x).__name__}")
    if x.device != device:
        raise ValueError(f"{name} is on {x.device} but the stream is on {device}; move it with .to({str(device)!r})")
    return x


class PillarStream:
    """A sliding time window of points, pillarized incrementally (per-pillar circular queues).

    Args:
        grid (PillarGrid): the pillar grid.
        window (float): window length in seconds (> 0), default 100 ms.
        max_points_per_pillar (int): N, the longest a pillar's queue may get.
        max_pillars (int): M, the most pillars active at once.
        device (str or torch.device): where the state and all outputs live (``"cpu"`` or ``"cuda"``).
        overflow (str): ``"raise"`` (default): a push that does not fit raises
            :class:`PillarOverflowError` and has no effect; ``"drop"``: the points that do not fit are
            dropped by a deterministic rule (the module docstring; ``docs/stream.md``) and counted
            in ``StreamUpdate.points_dropped``.
        cuda_graph (bool): on CUDA, run each push as one CUDA graph (default): the pushed points are
            padded to a power-of-two capacity (one graph per capacity, recorded by its first push or by
            :meth:`warm_up`), the window is decided on the device and the push's figures come back in one
            read. The same results as the eager push; ignored on the CPU, and while the stream's device
            is not the current CUDA device (``torch.cuda.set_device``), whose pushes run eagerly.

    Example::

        stream = PillarStream(PillarGrid.drone(), window=0.1, device="cuda")
        for points, t in sim.slices(0.0, 2.0, 0.01):      # float32 (n, 4), float64 (n,)
            update = stream.push(points, t)
            pillars = stream.pillars(update.changed[~update.removed])   # recompute these only

    Capacity: with ``overflow="raise"``, a push that would make a queue longer than N or occupy more
    than M pillars raises :class:`PillarOverflowError` naming the capacity and the count needed, and
    has no effect: the stream keeps the window it had before the call (checked before anything is
    changed). With ``overflow="drop"`` the push admits what fits: points already in the window stay;
    a pillar's entering points in (t, arrival) order while its queue has room; new pillars in key
    order while slots are free. The rest is dropped and counted.

    State (tensors on ``device``): a pool of M x N point slots (x, y, z, intensity float32 and t
    float64), per-slot head and count, an (H * W) map pillar -> slot (-1: empty), a stack of free
    slots, and a log of (pillar, t) entries in runs, one per push, each sorted by t: expiry pops the
    front of each run, so it visits only points that leave. See ``docs/stream.md``.
    """

    def __init__(self, grid: PillarGrid, window: float = 0.100, max_points_per_pillar: int = 100,
                 max_pillars: int = 12000, device: str | torch.device = "cpu", overflow: str = "raise",
                 cuda_graph: bool = True) -> None:
        self._grid = check_grid(grid)
        self.cuda_graph = cuda_graph
        if not isinstance(overflow, str) or overflow not in ("raise", "drop"):
            raise ValueError(f"overflow must be 'raise' or 'drop', got {overflow!r}")
        self._overflow = overflow
        # at least MIN_WINDOW: near MAX_ABS_TIME a shorter window rounds away (the newest point would fall out)
        if isinstance(window, bool) or not isinstance(window, (int, float)) \
                or not (MIN_WINDOW <= float(window) < float("inf")):
            raise ValueError(f"window must be a finite number of seconds >= {MIN_WINDOW:g} (timestamps are float64 "
                             f"seconds up to {MAX_ABS_TIME:g}), got {window!r}")
        self._window = float(window)
        self._N = check_capacity(max_points_per_pillar, "max_points_per_pillar")
        self._M = check_capacity(max_pillars, "max_pillars")
        try:
            self._device = torch.device(device)
        except (RuntimeError, TypeError):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}") from None
        if self._device.type not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}")
        if self._device.type == "cuda" and self._device.index is None and torch.cuda.is_available():
            # "cuda" means the current device; tensors report theirs with an index ("cuda:0")
            self._device = torch.device("cuda", torch.cuda.current_device())
        if self._device.type == "cuda" and not extension.cuda_available():
            raise extension.LidaropsBuildError(
                "PillarStream(device='cuda') but lidarops was built without CUDA kernels "
                f"({extension.build_info().get('cuda_reason', 'CPU-only build')})")
        self.reset()

    # ---- properties ----
    @property
    def grid(self) -> PillarGrid:
        return self._grid

    @property
    def window(self) -> float:
        return self._window

    @property
    def device(self) -> torch.device:
        return self._device

    @property
    def max_points_per_pillar(self) -> int:
        return self._N

    @property
    def max_pillars(self) -> int:
        return self._M

    @property
    def overflow(self) -> str:
        """``"raise"`` or ``"drop"``: what a push that does not fit does."""
        return self._overflow

    @property
    def cuda_graph(self) -> bool:
        """Whether a push on CUDA runs as one CUDA graph (settable: False pushes eagerly from then on)."""
        return self._cuda_graph and self._device.type == "cuda"

    @cuda_graph.setter
    def cuda_graph(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise ValueError(f"cuda_graph must be a bool, got {value!r}")
        self._cuda_graph = value

    @property
    def num_active(self) -> int:
        """Pillars holding at least one point."""
        return self._num_active

    @property
    def t(self) -> float:
        """``t_newest``: the largest timestamp seen (``-inf`` before the first point)."""
        return self._t

    @property
    def num_points(self) -> int:
        """Points in the window."""
        return self._num_points

    @property
    def counts(self) -> StreamCounts:
        """Cumulative point counts since creation or :meth:`reset`, invalid points included."""
        return self._counts

    # ---- state ----
    def reset(self) -> None:
        """Forget every point: an empty window, ``t_newest = -inf``."""
        M, N, dev = self._M, self._N, self._device
        i32 = dict(dtype=torch.int32, device=dev)
        self._pool_xyzi = torch.zeros((M, N, 4), dtype=torch.float32, device=dev)
        self._pool_t = torch.zeros((M, N), dtype=torch.float64, device=dev)
        self._head = torch.zeros(M, **i32)
        self._count = torch.zeros(M, **i32)
        self._slot_cell = torch.full((M,), -1, **i32)
        self._cell_slot = torch.full((self._grid.num_pillars,), -1, **i32)
        self._free_slots = torch.arange(M - 1, -1, -1, **i32)  # popped from the end: slot 0 first
        self._num_free = torch.full((1,), M, **i32)
        self._alloc_log(max(1024, min(M * N, 1 << 16)))
        self._runs: deque[list[int]] = deque()  # [start, end) absolute log positions, in push order
        self._log_head = 0
        self._t = float("-inf")
        self._num_active = 0
        self._num_points = 0
        self._counts = StreamCounts()

    def _alloc_log(self, length: int) -> None:
        self._push_graphs = {}  # they write the log they were recorded with
        self._log_cell = torch.full((length,), -1, dtype=torch.int32, device=self._device)
        self._log_t = torch.zeros(length, dtype=torch.float64, device=self._device)

    def _ensure_log_space(self, n: int) -> None:
        """Room for n more entries after the live runs: compact them to the front of a (possibly
        larger) log when the ring would wrap onto them. Amortised O(1) per entry."""
        L = self._log_cell.numel()
        start = self._runs[0][0] if self._runs else self._log_head
        if self._log_head - start + n <= L:
            return
        live = sum(e - s for s, e in self._runs)
        new_L = L
        while live + n > new_L // 2:
            new_L *= 2
        if self._runs:
            pos = torch.cat([torch.arange(s, e, dtype=torch.int64) for s, e in self._runs]).to(self._device) % L
            cells, times = self._log_cell.index_select(0, pos), self._log_t.index_select(0, pos)
        self._alloc_log(new_L)
        at = 0
        for run in self._runs:
            k = run[1] - run[0]
            run[0], run[1] = at, at + k
            at += k
        if self._runs:
            self._log_cell[:live] = cells
            self._log_t[:live] = times
        self._log_head = at

    # ---- the push ----
    def push(self, points, t, now: float | None = None) -> StreamUpdate:
        """Enqueue a slice of points, expire what left the window, report what changed.

        Args:
            points (Tensor[n, 4] float32 or ndarray): ``x, y, z, intensity``; a tensor must be on the
                stream's device (a NumPy array is copied there). n may be 0.
            t (Tensor[n] float64, ndarray, or a float for all points): timestamps in seconds, in any
                order (equal and out-of-order timestamps are fine).
            now (float, optional): advance ``t_newest`` to at least ``now`` (e.g. the end of the slice),
                so that points expire during a gap in the stream even without new points.

        Returns:
            StreamUpdate (see its docstring). Points with ``t <= t_newest - window`` never enter
            (``points_late``); points outside the grid never enter (``points_outside``); points whose
            intensity or ``t`` is NaN, infinite or beyond ``MAX_ABS_INTENSITY`` / ``MAX_ABS_TIME``
            never enter and do not move ``t_newest`` (``points_invalid``); with ``overflow="drop"``,
            points that do not fit never enter (``points_dropped``; they do move ``t_newest``).

        Raises:
            ValueError: bad arguments (shapes, dtypes, devices; ``now`` not a finite number of
                seconds within ``MAX_ABS_TIME``). Point values never raise.
            PillarOverflowError: with ``overflow="raise"``, a capacity would be exceeded; the push had
                no effect.
            RuntimeError: the stream's state tensors were corrupted (changed from outside the
                class); the message names the tensor and the bad value, and the push had no effect.
        """
        dev = self._device
        points = _as_tensor(points, "points", dev)
        if points.dim() != 2 or points.shape[1] != 4 or points.dtype != torch.float32:
            raise ValueError(f"points must be float32 (n, 4): x, y, z, intensity, got {describe(points)}")
        n = points.shape[0]
        if isinstance(t, (int, float)) and not isinstance(t, bool):
            t = torch.full((n,), float(t), dtype=torch.float64, device=dev)
        t = _as_tensor(t, "t", dev)
        if t.dim() != 1 or t.shape[0] != n or t.dtype != torch.float64:
            raise ValueError(f"t must be float64 (n,) with n = {n} (float32 cannot hold timestamps to the "
                             f"microsecond), got {describe(t)}")
        if now is not None:
            if isinstance(now, bool) or not isinstance(now, (int, float)) or not abs(now) <= MAX_ABS_TIME:
                raise ValueError(f"now must be a finite number of seconds with |now| <= {MAX_ABS_TIME:g}, got {now!r}")
        # a graph records and replays on the current device's stream: a stream on another device pushes eagerly
        if self.cuda_graph and dev.index == torch.cuda.current_device() \
                and not torch.cuda.is_current_stream_capturing():
            floor = self._t if now is None else max(self._t, float(now))
            graphed = self._graph_push(points, t, floor)
            if graphed is not None:
                return self._commit(*graphed)
        newest = self._t
        n_invalid = bad_i = bad_t = 0
        if n:
            # the input policy: invalid points are moved outside the grid (counted as outside by the
            # op, subtracted below) and left out of t_newest; their counts come with the newest time
            bad_intensity, bad_time = invalid_points(points, t)
            invalid = bad_intensity | bad_time
            t_max = torch.where(invalid, float("-inf"), t).max()
            counts = torch.stack([invalid.sum(), bad_intensity.sum(), bad_time.sum()]).to(torch.float64)
            t_max, n_invalid, bad_i, bad_t = torch.cat([t_max.view(1), counts]).tolist()  # exact below 2^53
            n_invalid, bad_i, bad_t = int(n_invalid), int(bad_i), int(bad_t)
            if n_invalid:
                points = without_invalid(points, invalid)
                t = torch.where(invalid, 0.0, t)
            newest = max(newest, t_max)
        if now is not None:
            newest = max(newest, float(now))
        cutoff = newest - self._window  # -inf before the first timestamp: nothing expires
        self._ensure_log_space(n)
        runs = torch.tensor(list(self._runs), dtype=torch.int64).reshape(-1, 2)
        if dev.type == "cuda":  # pinned and asynchronous: a pageable copy would wait for the device
            runs = runs.pin_memory().to(dev, non_blocking=True)
        # with overflow="drop" the op admits what fits by the rule above and counts the rest
        change_map, st, pops, n_changed = self._push_op(points, t, runs, cutoff)

        def outputs():  # the lengths are known on the host: nonzero_static does not wait for the device
            changed_yx = torch.nonzero_static(change_map, size=n_changed)
            keys = changed_yx[:, 0] * self._grid.shape[1] + changed_yx[:, 1]
            return (self.active_coords(), _batch0(changed_yx), self._cell_slot.index_select(0, keys) < 0,
                    change_map)

        return self._commit(n, newest, n_invalid, bad_i, bad_t, st, pops, outputs)

    def _commit(self, n: int, newest: float, n_invalid: int, bad_i: int, bad_t: int, st: list, pops: list,
                outputs) -> StreamUpdate:
        """After the op: raise for an overflow or a corrupt state (the push had no effect), else commit the
        host's bookkeeping and return the update (``outputs()``: active, changed, removed, change_map)."""
        if st[_P_OVERFLOW] & ~_OVERFLOW_BITS:
            raise RuntimeError(self._corruption_message(st[_P_OVERFLOW], st[_P_EMPTIED]))
        if st[_P_OVERFLOW] and self._overflow == "raise":
            raise PillarOverflowError(
                overflow_message("PillarStream.push", f"the window ({newest - self._window!r}, {newest!r}]",
                                  st[_P_MAX_POINTS], self._N, st[_P_PILLARS], self._M)
                + " when creating the PillarStream, or create it with overflow='drop' (the points that do not "
                  "fit are dropped by a documented rule and counted). The push had no effect: the stream still "
                  "holds its previous window")
        if st[_P_OVERFLOW]:  # the rule admits only what fits: this is a bug, not an input
            raise RuntimeError(f"PillarStream.push: the points kept by overflow='drop' still do not fit "
                               f"(flags {st[_P_OVERFLOW]}); please report this")
        drop_points, drop_pillars = st[_P_DROPPED_POINTS], st[_P_DROPPED_PILLARS]
        n_dropped = drop_points + drop_pillars
        # commit the host-side bookkeeping
        self._t = newest
        for run, k in zip(self._runs, pops):
            run[0] += k
        self._runs = deque(r for r in self._runs if r[0] < r[1])
        if st[_P_IN]:
            self._runs.append([self._log_head, self._log_head + st[_P_IN]])
            self._log_head += st[_P_IN]
        self._num_active = st[_P_PILLARS]
        self._num_points += st[_P_IN] - st[_P_OUT]
        outside = st[_P_OUTSIDE] - n_invalid
        c = self._counts
        self._counts = StreamCounts(c.points_pushed + n, c.points_in + st[_P_IN], c.points_out + st[_P_OUT],
                                    c.points_outside + outside, c.points_late + st[_P_LATE],
                                    c.points_invalid + n_invalid, c.invalid_intensity + bad_i, c.invalid_t + bad_t,
                                    c.points_dropped + n_dropped, c.dropped_max_points + drop_points,
                                    c.dropped_max_pillars + drop_pillars)
        active, changed, removed, change_map = outputs()
        return StreamUpdate(self._t, active, changed, removed, change_map,
                            st[_P_IN], st[_P_OUT], outside, st[_P_LATE], n_invalid, n_dropped)

    # ---- the push as a CUDA graph ----
    def warm_up(self, points: int = 16384) -> int:
        """Record now the CUDA graphs of pushes of up to ``points`` points (one per power-of-two capacity from
        1024), which the first push of each capacity would otherwise record. Returns how many it recorded (0 on
        the CPU, with ``cuda_graph=False``, or when the stream's device is not the current one). Growing the log
        (a window holding more points than it has held before) records them again."""
        if isinstance(points, bool) or not isinstance(points, int) or points < 0:
            raise ValueError(f"points must be an int >= 0, got {points!r}")
        if not self.cuda_graph or self._device.index != torch.cuda.current_device():
            return 0
        rcap = graph_capacity(len(self._runs), 16)
        known = len(self._push_graphs)
        for k in range(10, graph_capacity(points, 1024).bit_length()):
            if (1 << k) <= self._log_cell.numel():
                self._push_graph(1 << k, rcap)
        return len(self._push_graphs) - known

    def _graph_push(self, points: Tensor, t: Tensor, floor: float):
        """The push as one CUDA graph: the points copied into the graph's buffers (the rows past them padding,
        invalid), the runs, the log head and the window's floor (``max(t_newest, now)``) in one copy from pinned
        memory, the graph replayed and its figures read once. Returns ``_commit``'s arguments, or None when the
        log cannot hold the padded points (the eager push then runs)."""
        n = points.shape[0]
        cap = graph_capacity(n, 1024)
        self._ensure_log_space(n)
        if cap > self._log_cell.numel():
            return None
        R = len(self._runs)
        rec = self._push_graph(cap, graph_capacity(R, 16))
        host = rec["host_np"]
        host[0], host[1] = n, self._log_head
        host[2:3].view(np.float64)[0] = floor
        host[3:] = 0
        if R:
            host[3:3 + 2 * R] = np.asarray(self._runs, dtype=np.int64).ravel()
        rec["scalars"].copy_(rec["host"], non_blocking=True)  # the last push's read finished the previous copy
        if n:
            rec["points"][:n].copy_(points)
            rec["t"][:n].copy_(t)
        rec["graph"].replay()
        vals = rec["figures"].tolist()
        rcap = rec["rcap"]
        st = vals[:_NUM_STATS]
        st[_P_OUTSIDE] -= cap - n  # the padding rows count as outside the grid
        n_changed, n_invalid, bad_i, bad_t, newest_bits = vals[_NUM_STATS + rcap:]
        newest = float(np.array(newest_bits, dtype=np.int64).view(np.float64))
        active, changed, removed, change_map = rec["outputs"]

        def outputs():  # copies: the graph's buffers are the next push's
            return (active[:st[_P_PILLARS]].clone(), changed[:n_changed].clone(), removed[:n_changed].clone(),
                    change_map.clone())

        return n, newest, n_invalid, bad_i, bad_t, st, vals[_NUM_STATS:_NUM_STATS + R], outputs

    def _push_graph(self, cap: int, rcap: int) -> dict:
        """The graph of a push of up to ``cap`` points with up to ``rcap`` runs, recorded on first use."""
        rec = self._push_graphs.get((cap, rcap))
        if rec is not None:
            return rec
        dev, g = self._device, self._grid
        H, W = g.shape
        host = torch.zeros(3 + 2 * rcap, dtype=torch.int64).pin_memory()
        rec = {"cap": cap, "rcap": rcap, "host": host, "host_np": host.numpy(),
               "scalars": torch.zeros(3 + 2 * rcap, dtype=torch.int64, device=dev),
               "points": torch.zeros((cap, 4), dtype=torch.float32, device=dev),
               "t": torch.zeros(cap, dtype=torch.float64, device=dev),
               "rows": torch.arange(cap, device=dev)}
        changed_rows = min(2 * self._M, H * W)  # pillars that gained or lost points: active before or after

        def body():
            sc = rec["scalars"]
            row_ok = rec["rows"] < sc[0]
            pts, tt = rec["points"], rec["t"]
            bad_i, bad_t = invalid_points(pts, tt)
            bad_i, bad_t = bad_i & row_ok, bad_t & row_ok
            bad = bad_i | bad_t
            invalid = bad | ~row_ok
            newest = torch.maximum(torch.where(invalid, float("-inf"), tt).max().view(1),
                                   sc[2:3].view(torch.float64))
            op_scalars = torch.cat([sc[1:2], (newest - self._window).view(torch.int64)])
            change_map, stats, run_pops = torch.ops.lidarops.pillar_stream_push(
                self._pool_xyzi, self._pool_t, self._head, self._count, self._slot_cell, self._cell_slot,
                self._free_slots, self._num_free, self._log_cell, self._log_t, without_invalid(pts, invalid),
                torch.where(invalid, 0.0, tt), sc[3:].view(rcap, 2), 0, 0.0, list(g.point_cloud_range),
                list(g.pillar_size), list(g.shape), self._overflow == "drop", op_scalars)
            figures = torch.cat([stats, run_pops, change_map.sum().view(1), bad.sum().view(1), bad_i.sum().view(1),
                                 bad_t.sum().view(1), newest.view(torch.int64)])
            changed_yx = torch.nonzero_static(change_map, size=changed_rows, fill_value=0)
            keys = changed_yx[:, 0] * W + changed_yx[:, 1]
            removed = self._cell_slot.index_select(0, keys) < 0
            active = torch.nonzero_static(self._cell_slot.view(H, W) >= 0, size=self._M, fill_value=0)
            return figures, (_batch0(active), _batch0(changed_yx), removed, change_map)

        rec["host_np"][1] = self._log_head  # the warm-up's push: no points, empty runs: it changes nothing
        rec["host_np"][2:3].view(np.float64)[0] = float("-inf")
        rec["scalars"].copy_(rec["host"])
        pool = next(iter(self._push_graphs.values()))["graph"].pool() if self._push_graphs else None
        with torch.no_grad(), uncached_autocast():
            rec["graph"], (rec["figures"], rec["outputs"]) = record_graph(body, dev, pool=pool)
        self._push_graphs[(cap, rcap)] = rec
        return rec

    def _push_op(self, points: Tensor, t: Tensor, runs: Tensor, cutoff: float):
        """One call of the op; returns (change_map, stats, run pops, changed count) with the figures
        read in the push's one device-to-host copy."""
        g = self._grid
        change_map, stats, run_pops = torch.ops.lidarops.pillar_stream_push(
            self._pool_xyzi, self._pool_t, self._head, self._count, self._slot_cell, self._cell_slot,
            self._free_slots, self._num_free, self._log_cell, self._log_t, points.contiguous(), t.contiguous(),
            runs, self._log_head, cutoff, list(g.point_cloud_range), list(g.pillar_size), list(g.shape),
            self._overflow == "drop")
        vals = torch.cat([stats, run_pops, change_map.sum().view(1)]).tolist()
        return change_map, vals[:_NUM_STATS], vals[_NUM_STATS:-1], vals[-1]

    def _corruption_message(self, flags: int, emptied: int) -> str:
        """Why pillar_stream_push refused the state (its kPsBad* flags), with the first bad value found
        by a full check on the host (an error path: the push itself checks only what it reads)."""
        M, N, C = self._M, self._N, self._grid.num_pillars
        head, count, slot_cell, cell_slot = (x.cpu() for x in (self._head, self._count, self._slot_cell,
                                                                self._cell_slot))
        free_slots, num_free = self._free_slots.cpu(), int(self._num_free[0])
        why = []

        def first(mask: Tensor):
            i = torch.nonzero(mask).view(-1)
            return int(i[0]) if i.numel() else None

        if flags & _BAD_RUNS:
            why.append(f"the runs of the log are not inside the log of length {self._log_cell.numel()}: "
                       f"{list(self._runs)}")
        if flags & _BAD_LOG:
            why.append("log_cell: an expiring log entry names a cell outside [0, H * W) or an empty pillar")
        if flags & _BAD_CELL_SLOT:
            i = first((cell_slot < -1) | (cell_slot >= M))
            if i is not None:
                why.append(f"cell_slot[{i}] = {int(cell_slot[i])} is outside [-1, max_pillars = {M})")
            else:
                why.append("cell_slot and slot_cell disagree: a pillar's slot does not name the pillar back")
        if flags & _BAD_QUEUE:
            i, j = first((head < 0) | (head >= N)), first((count < 0) | (count > N))
            if i is not None:
                why.append(f"head[{i}] = {int(head[i])} is outside [0, max_points_per_pillar = {N})")
            if j is not None:
                why.append(f"count[{j}] = {int(count[j])} is outside [0, max_points_per_pillar = {N}]")
            if i is None and j is None:
                why.append("count: more of a queue's points expire than it holds (the log and count disagree)")
        if flags & _BAD_NUM_FREE:
            why.append(f"num_free = {num_free} is outside [0, max_pillars = {M}]" if not 0 <= num_free <= M else
                       f"num_free = {num_free} leaves no room for the {emptied} slots the push frees "
                       f"(max_pillars = {M})")
        if flags & _BAD_FREE_SLOTS:
            top = free_slots[:max(0, min(num_free, M))].to(torch.int64)
            bad = (top < 0) | (top >= M)
            bad |= ~bad & (slot_cell[top.clamp(0, M - 1)] != -1)
            i = first(bad)
            why.append(f"free_slots[{i}] = {int(top[i])} is outside [0, max_pillars = {M}) or a slot in use"
                       if i is not None else "free_slots holds a slot that is outside [0, max_pillars) or in use")
        return ("PillarStream.push: the stream's state is corrupt (changed from outside the class?): "
                + "; ".join(why) + f" (grid of {C} pillars). The push had no effect; call reset() to start over")

    # ---- reading the window ----
    def active_coords(self) -> Tensor:
        """int32 (A, 3): ``(0, y, x)`` of the non-empty pillars, sorted by key."""
        yx = torch.nonzero_static(self._cell_slot.view(self._grid.shape) >= 0, size=self._num_active)
        return _batch0(yx)

    def pillars(self, coords: Tensor | None = None, check: bool = True) -> Pillars:
        """Decorated features of active pillars, in the given order.

        Args:
            coords (int Tensor[P, 3] or None): ``(batch=0, y, x)`` of active pillars (e.g.
                ``update.changed[~update.removed]``); default: every active pillar, sorted by key.
            check (bool): check the coords and the state (one wait for the device). ``False`` is for
                coords the stream itself returned (``StreamUpdate.active`` / ``changed``, int32): no
                host synchronisation; a pillar that is empty then gives zero points and features, and
                one whose state is out of range -1 points (the op never indexes with it).

        Returns:
            Pillars: features (P, max_points_per_pillar, 9) float32 (points in time order, ties in
            arrival order), coords int32 (P, 3), num_points int32 (P,).

        Raises:
            ValueError: coords of the wrong shape, dtype or device, outside the grid, or of a pillar
                that is not active.
        """
        if check not in (True, False):
            raise ValueError(f"check must be True or False, got {check!r}")
        if not check and coords is not None:
            return self._gather(coords)
        H, W = self._grid.shape
        given = None  # the coords as the caller gave them, for the error message
        if coords is None:
            coords = self.active_coords()
        else:
            coords = _as_tensor(coords, "coords", self._device)
            if coords.dim() != 2 or coords.shape[1] != 3 or coords.is_floating_point() or coords.is_complex() \
                    or coords.dtype == torch.bool:
                raise ValueError(f"coords must be an integer (P, 3) tensor of (batch, y, x), got {describe(coords)}")
            # out-of-grid values become -1 before the int32 cast: a huge int64 would wrap into the grid
            given = coords.to(torch.int64)
            limit = torch.tensor([1, H, W], device=given.device)
            coords = torch.where((given >= 0) & (given < limit), given, -1).to(torch.int32)
        keys = coords[:, 1].to(torch.int64) * W + coords[:, 2].to(torch.int64)
        pillars = self._gather(coords, keys)
        if coords.shape[0]:
            b, y, x = coords.unbind(1)
            inside = (b == 0) & (y >= 0) & (y < H) & (x >= 0) & (x < W)
            active = inside & (self._cell_slot.index_select(0, torch.where(inside, keys, 0)) >= 0)
            # the gather reports -1 points for a pillar whose slot, head or count is out of range
            bad = (~active | (pillars.num_points < 0)).nonzero()  # one wait for the device, for both checks
            if bad.numel():
                i = int(bad[0, 0])
                if not bool(active[i]):
                    raise ValueError(f"coords[{i}] = {(given if given is not None else coords)[i].tolist()} is not an "
                                     "active pillar of the stream "
                                     f"({bad.shape[0]} of {coords.shape[0]} coords are not; grid {H} x {W}, "
                                     f"batch 0)")
                s = int(self._cell_slot[keys[i]])
                what = (f"cell_slot[{int(keys[i])}] = {s} is outside [0, max_pillars = {self._M})"
                        if not 0 <= s < self._M else
                        f"head[{s}] = {int(self._head[s])}, count[{s}] = {int(self._count[s])} (expected "
                        f"0 <= head < {self._N} and 0 <= count <= {self._N})")
                raise RuntimeError(f"PillarStream.pillars: the stream's state is corrupt (changed from outside the "
                                   f"class?): pillar coords[{i}] = {coords[i].tolist()}: {what}; call reset()")
        return pillars

    def _gather(self, coords: Tensor, keys: Tensor | None = None) -> Pillars:
        """:meth:`pillars` of int32 ``(0, y, x)`` coords inside the grid, without the checks (no host
        synchronisation); a pillar that is empty gives zero points and zero features (and one whose
        state is out of range -1 points: the op never indexes with it)."""
        if keys is None:
            keys = coords[:, 1].to(torch.int64) * self._grid.shape[1] + coords[:, 2].to(torch.int64)
        raw, num_points = torch.ops.lidarops.pillar_stream_gather(self._pool_xyzi, self._head, self._count,
                                                                  self._cell_slot, keys)
        return Pillars(decorate_pillars(raw, num_points, coords, self._grid), coords, num_points)

    def __repr__(self) -> str:
        return (f"PillarStream({self._grid!r}, window={self._window}, max_points_per_pillar={self._N}, "
                f"max_pillars={self._M}, device={str(self._device)!r}; t={self._t}, "
                f"{self._num_active} active pillars, {self._num_points} points)")


def _batch0(yx: Tensor) -> Tensor:
    """(K, 2) int64 (y, x) -> (K, 3) int32 (0, y, x)."""
    out = torch.zeros((yx.shape[0], 3), dtype=torch.int32, device=yx.device)
    out[:, 1:] = yx
    return out
