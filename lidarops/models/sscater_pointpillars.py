"""SSCATeR PointPillars: a LiDAR stream -> pillars -> PillarFeatureNet -> recycling backbone
(:class:`lidarops.sscater.DeltaBackbone`).

Each :meth:`SSCATeRPointPillars.step` consumes one slice of points (10 ms in the paper), slides the
window (:class:`lidarops.stream.PillarStream`), runs the pillar feature net only on the pillars that
gained or lost points, and updates the backbone by delta convolution
(:class:`lidarops.sscater.delta.DeltaBackbone`). The result equals ``backbone(mode="sparse")`` on the
pillarized window with the same weights, up to float rounding; ``refresh_every`` full recomputations
bound the drift of the recycled sums (docs/sscater.md measures it).

Input policy: the stream's (``docs/stream.md``): points whose intensity or timestamp is NaN, infinite
or beyond ``MAX_ABS_INTENSITY`` / ``MAX_ABS_TIME`` are dropped and counted (``stats.points_invalid``,
``model.stream.counts``), so they never reach the recycled state; :meth:`recompute` (``pillarize``)
applies the same rule. Overflow: the stream's (``overflow="raise" | "drop"``, passed through): with
"drop", the points that do not fit are dropped by the stream's documented rule and counted
(``stats.points_dropped``), and the output equals :meth:`recompute` of the points actually kept.
Guard: after every step the largest accumulator magnitude is checked (one
reduction); a non-finite value, or a swing by more than ``guard_ratio`` (a value entered, or left and
would leave its rounding residue behind), forces a full refresh within the same step, reported in
``stats.guard`` and counted in ``stats.guard_refreshes``.
"""
from __future__ import annotations

import copy
import functools
import math
import time
from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops._cuda_graphs import graph_capacity, record_graph, uncached_autocast
from lidarops.models.bev_backbone import BaseBEVBackbone
from lidarops.ops.validation import check_tensor, describe, validation, value_checks_enabled
from lidarops.sscater import delta as delta_module
from lidarops.sscater.delta import DeltaBackbone, LayerStats

__all__ = ["DETECT_CUDA_GRAPH", "HEAD_DENSE_SHARE", "SSCATeRPointPillars", "StepStats", "PillarFeatureNet",
           "DetectorPFN"]

# Share of the head's output sites changed since the last detect() from which the head runs as one dense 1x1
# convolution over the map: gathering and scattering most of the map's rows costs more than the convolution
# (measured in docs/sscater.md).
HEAD_DENSE_SHARE = 0.5

# detect() on CUDA replays the head, its decode and the post-processing as one CUDA graph (the head is dense
# there: the step's site lists stay on the device). Eager, they launch about a hundred kernels and read sizes back
# to the host twice; the graph's only read is the number of boxes.
DETECT_CUDA_GRAPH = True


# SSCATeR's own pillar net, kept until SSCATeR runs the detector's PillarVFE: the stream gathers 9-feature
# pillars (lidarops.ops.pillars) whose padding slots must not enter BatchNorm or the max, so that a pillar's
# features depend on its own points only and an unchanged pillar need not be recomputed.
class PillarFeatureNet(nn.Module):
    """Pillar feature net: one PointNet layer over the points of each pillar.

    Args:
        in_channels (int): decorated features per point (9: x, y, z, intensity, offsets to the pillar's
            mean, offsets x, y to the pillar centre).
        out_channels (int): features per pillar.

    Shape:
        ``forward(pillars)`` takes anything with ``features (Tensor[P, N, in_channels])`` and
        ``num_points (Tensor[P])`` (the ``Pillars`` of :func:`lidarops.ops.pillarize`) and returns
        Tensor[P, out_channels] in the parameters' dtype (features are cast to it), rows in the
        pillars' order. Slots at or beyond ``num_points[p]`` are
        padding: they take no part in BatchNorm's batch statistics nor in the max.
    """

    def __init__(self, in_channels: int = 9, out_channels: int = 64):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.linear = nn.Linear(in_channels, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, pillars) -> Tensor:
        features, num_points = pillars.features, pillars.num_points
        check_tensor(features, "pillars.features")
        if features.dim() != 3 or features.shape[2] != self.in_channels:
            raise ValueError(f"pillars.features must be (P, N, {self.in_channels}), got {describe(features)}")
        if num_points.dim() != 1 or num_points.shape[0] != features.shape[0]:
            raise ValueError(f"pillars.num_points must be ({features.shape[0]},), got {describe(num_points)}")
        # pillarize / PillarStream give float32 features (the points' dtype); a float64 net widens them
        features = features.to(self.linear.weight.dtype)
        P, N, _ = features.shape
        mask = torch.arange(N, device=features.device) < num_points.to(features.device).long()[:, None]  # (P, N)
        if not N or not P:
            return features.new_zeros(P, self.out_channels)
        if features.is_cuda and not self.training:
            # every slot, padding masked to zero afterwards: no boolean indexing, so no host sync
            # (eval mode only: BatchNorm's batch statistics must see the real points alone)
            x = torch.relu(self.norm(self.linear(features.reshape(P * N, -1)))).view(P, N, -1)
            out = torch.where(mask[..., None], x, x.new_zeros(()))
        else:  # only the real points (on CPU the padding would multiply the work)
            x = self.linear(features[mask])
            x = torch.relu(self.norm(x)) if x.shape[0] else x
            out = features.new_zeros(P, N, self.out_channels)
            out[mask] = x
        # post-ReLU values are >= 0, so zero padding never wins the max over a non-empty pillar
        return out.amax(dim=1)


class DetectorPFN(nn.Module):
    """A trained detector's pillar net (OpenPCDet's ``PillarVFE``) on the stream's pillars: their points (x, y,
    z, intensity: the first four decorated features) and counts, with the VFE's own decorations and padding
    (empty slots enter its max, as in the detector), so a pillar's features are the detector's for the same
    points. An emptied pillar (no points) gives zeros: the detector's BEV image holds zeros where no pillar is.

    Args:
        vfe (lidarops.models.pillar_vfe.PillarVFE): the detector's ``vfe``, in eval mode.
        max_points (int): the detector's ``MAX_POINTS_PER_VOXEL``: its slots per pillar (the stream must hold as
            many, so that the padding entering the max is the same).
    """

    def __init__(self, vfe: nn.Module, max_points: int):
        super().__init__()
        self.vfe = vfe
        self.max_points = int(max_points)
        self.out_channels = int(vfe.pfn_layers[-1].linear.out_features * (1 if vfe.pfn_layers[-1].last_vfe else 2))

    def forward(self, pillars) -> Tensor:
        features, num_points = pillars.features, pillars.num_points
        if features.dim() != 3 or features.shape[1] != self.max_points:
            raise ValueError(f"pillars.features must be (P, {self.max_points}, C) (the detector's slots per pillar), "
                             f"got {describe(features)}")
        weight = self.vfe.pfn_layers[0].linear.weight
        coords = pillars.coords.to(torch.int32)
        coords4 = torch.cat([coords[:, :1], torch.zeros_like(coords[:, :1]), coords[:, 1:]], 1)
        out = self.vfe(features[:, :, :4].to(weight.dtype), num_points, coords4)
        return torch.where(num_points[:, None] > 0, out, out.new_zeros(()))




@dataclass
class StepStats:
    """Figures of the last step.

    Attributes:
        step (int), t (float): step index since reset and the window's newest time.
        refreshed (bool): the step was a full recomputation.
        points_in, points_out (int): points that entered / left the window.
        pillars_active, pillars_changed (int): non-empty pillars, and those that gained or lost points.
        pfn_points, pfn_points_full (int): points run through the PFN, and what a full recomputation
            would run (the PFN's work is proportional to its points).
        ms_stream, ms_pfn, ms_backbone (float): wall time of each stage (a guard refresh counts in
            ``ms_backbone``; so does a recycled step's pillar net where it runs inside the backbone's CUDA
            graph).
        layers (list[LayerStats]): per-layer active / changed / touched sites and times.
        points_invalid (int): points of the slice dropped by the stream's input policy (intensity or t
            NaN, infinite or out of bounds); cumulative counts in ``model.stream.counts``.
        points_dropped (int): points of the slice that did not fit the stream's capacities
            (``overflow="drop"``; always 0 with "raise").
        state_max (float or None): max |acc| over the backbone's accumulators after the step (NaN or
            inf if one is not finite); None with ``guard=False``.
        guard (str): why the guard forced a full refresh in this step, or that even a full
            recomputation is not finite (non-finite pillar features or weights); "" when all is well.
        guard_refreshes (int): refreshes forced by the guard since :meth:`reset` (this step included).
    """

    step: int = 0
    t: float = 0.0
    refreshed: bool = False
    points_in: int = 0
    points_out: int = 0
    pillars_active: int = 0
    pillars_changed: int = 0
    pfn_points: int = 0
    pfn_points_full: int = 0
    ms_stream: float = 0.0
    ms_pfn: float = 0.0
    ms_backbone: float = 0.0
    layers: list = field(default_factory=list)
    points_invalid: int = 0
    state_max: Optional[float] = None
    guard: str = ""
    guard_refreshes: int = 0
    points_dropped: int = 0

    @property
    def pfn_saved(self) -> float:
        """Share of the PFN's work saved by recomputing only the changed pillars."""
        return 1.0 - self.pfn_points / self.pfn_points_full if self.pfn_points_full else 0.0


class SSCATeRPointPillars:
    """Streaming PointPillars front (PFN + backbone) with temporal data recycling.

    Args:
        pfn (PillarFeatureNet), backbone (BaseBEVBackbone): the model, used in eval mode; its
            parameters are read at construction (call :meth:`reset` with ``reload=True`` after changing them).
        grid (lidarops.stream.PillarGrid): pillar grid; H and W divisible by 8 with the default backbone.
        window (float): window length in seconds (100 ms in the paper).
        max_points_per_pillar, max_pillars (int): capacities of the stream.
        overflow (str): the stream's overflow policy: ``"raise"`` (default: a slice that does not fit
            raises :class:`~lidarops.stream.PillarOverflowError` and the step has no effect) or
            ``"drop"`` (the points that do not fit are dropped by the rule of
            :class:`~lidarops.stream.PillarStream` and counted in ``stats.points_dropped``).
        refresh_every (int): full recomputation every N steps (0: never after the first). Bounds the
            float drift of the recycled sums: in float32 the difference to a full recomputation grows by
            about 1e-7 of max|output| per step on drone_bridge (1.1e-5 after 90 steps), so the default
            25 keeps it well under 1e-5; see docs/sscater.md.
        dtype (torch.dtype): float32 or float64 state.
        device: where everything runs (default: the backbone's device).
        profile (bool): time each layer (synchronises CUDA between layers).
        guard (bool): check the recycled state after every step (max |acc| over every accumulator:
            one reduction, read with the step's figures) and refresh it in the same step when the
            check trips: a non-finite value; a jump by more than ``guard_ratio`` in one step (a huge
            value entered, or the state was corrupted); or a fall by more than ``guard_ratio`` from
            its peak since the last refresh (what entered and left leaves float rounding residue of
            about 2^-24 of the peak in float32, which a smaller state cannot absorb).
        guard_ratio (float, optional): default 16 in float32 (a 16x swing leaves a residue of about
            1e-6 of the output; on simulated streams the state's magnitude swings by at most 1.7x),
            1024 in float64.

    ``step(points, t)`` returns Tensor[1, C, H/2, W/2] (C = 384 by default): the state itself, valid
    until the next step (clone it to keep it). ``stats`` describes the last step.
    """

    def __init__(self, pfn: PillarFeatureNet, backbone: BaseBEVBackbone, grid, window: float = 0.1,
                 max_points_per_pillar: int = 100, max_pillars: int = 12000, refresh_every: int = 25,
                 dtype: torch.dtype = torch.float32, device=None, profile: bool = False, guard: bool = True,
                 guard_ratio: Optional[float] = None, overflow: str = "raise", dense: bool = False):
        from lidarops.stream import PillarStream
        if pfn.training or backbone.training:
            raise ValueError("pfn and backbone must be in eval mode (call .eval()): SSCATeR folds BatchNorm's "
                             "running statistics")
        if pfn.out_channels != backbone.in_channels:
            raise ValueError(f"pfn.out_channels ({pfn.out_channels}) must equal backbone.in_channels "
                             f"({backbone.in_channels})")
        if isinstance(refresh_every, bool) or not isinstance(refresh_every, int) or refresh_every < 0:
            raise ValueError(f"refresh_every must be an int >= 0, got {refresh_every!r}")
        if guard_ratio is None:
            guard_ratio = 1024.0 if dtype == torch.float64 else 16.0
        if isinstance(guard_ratio, bool) or not isinstance(guard_ratio, (int, float)) or not 1 < guard_ratio < math.inf:
            raise ValueError(f"guard_ratio must be a finite number > 1, got {guard_ratio!r}")
        backbone.output_shape(grid.shape)  # the grid must suit the backbone
        self.pfn, self.backbone, self.grid = pfn, backbone, grid
        self.device = torch.device(device) if device is not None else next(backbone.parameters()).device
        self.dtype, self.refresh_every, self.profile = dtype, refresh_every, profile
        self.stream = PillarStream(grid, window, max_points_per_pillar, max_pillars, device=self.device,
                                   overflow=overflow)
        self.delta = DeltaBackbone(backbone, grid.shape, dtype, self.device, state_check=guard)
        self.guard, self.guard_ratio = bool(guard), float(guard_ratio)
        if dense not in (True, False):
            raise ValueError(f"dense must be True or False, got {dense!r}")
        # dense: every pillar site is active (zero features where no pillar is), so each convolution is the
        # dense backbone's (zero padding at the map's edges, BatchNorm's shift everywhere), as a detector
        # trained with the dense backbone computes it
        self.dense = bool(dense)
        self.detector = None  # the PointPillars whose head and post-processing turn the map into boxes
        self._head: Optional[dict] = None  # the head's output maps on the recycled map (detect)
        self._head_sites: Optional[list] = None  # output sites changed since the last detect; None: all
        self._detect_graph: Optional[tuple] = None  # (precision flags, config, graph, head maps, padded boxes)
        self._pfn_points = torch.zeros((), dtype=torch.int64, device=self.device)  # written by _changed_features
        self._all_sites: Optional[Tensor] = None  # (H * W, 2) every site, for the dense mode's refresh
        self._refresh_inputs: dict = {}  # a graphed refresh's padded pillar list and features function, by capacity
        self.stats = StepStats()
        self._since_refresh: Optional[int] = None
        self._state_peak = self._state_prev = 0.0  # max |acc|: largest since the last refresh, last step's

    @property
    def window(self) -> float:
        return self.stream.window

    def reset(self, reload: bool = False) -> None:
        """Empty the window; the next step is a full recomputation. ``reload`` re-reads the weights."""
        self.stream.reset()
        if reload:
            self.delta.reload()
        self._since_refresh = None
        self._state_peak = self._state_prev = 0.0
        self.stats = StepStats()
        self._head = self._head_sites = None
        self._detect_graph = None  # a reload may give the output map new memory

    def _pfn(self, pillars) -> Tensor:
        with torch.no_grad():
            return self.pfn(pillars).to(self.dtype)

    def _changed_features(self, sites: Tensor) -> Tensor:
        """The pillar net's features of the changed pillars at ``sites`` (int32 (n, 2); rows (-1, -1) are a CUDA
        graph's padding, which the stream's gather gives no points), for :meth:`DeltaBackbone.update` to run inside
        its graph; their points are counted in ``_pfn_points``."""
        pillars = self.stream.pillars(F.pad(sites, (1, 0)), check=False)
        self._pfn_points.copy_(pillars.num_points.sum())
        return self._pfn(pillars)

    def _mark(self):
        """A point in time: a CUDA event on CUDA (read after the step's final synchronisation, so the
        stages are timed without synchronising between them), else the host clock."""
        if self.device.type == "cuda":
            ev = torch.cuda.Event(enable_timing=True)
            ev.record(torch.cuda.current_stream(self.device))
            return ev
        return time.perf_counter()

    def _elapsed(self, a, b) -> float:
        return a.elapsed_time(b) if self.device.type == "cuda" else (b - a) * 1e3

    def step(self, points, t, now: Optional[float] = None) -> Tensor:
        """Consume one slice: ``points (Tensor[n, 4] float32)``, ``t (Tensor[n] float64)`` seconds (on
        the model's device, or NumPy arrays). ``now`` advances the window's end (e.g. the slice's end
        time) so that points expire during gaps in the stream."""
        st = StepStats(step=self.stats.step + 1 if self._since_refresh is not None else 0,
                       guard_refreshes=self.stats.guard_refreshes if self._since_refresh is not None else 0)
        m0 = self._mark()
        upd = self.stream.push(points, t, now=now)  # its figures are read on the host: it synchronises
        st.t, st.points_in, st.points_out, st.points_invalid = upd.t, upd.points_in, upd.points_out, upd.points_invalid
        st.points_dropped = upd.points_dropped
        st.pillars_active, st.pillars_changed = int(upd.active.shape[0]), int(upd.changed.shape[0])
        m1 = self._mark()
        refresh = self._since_refresh is None or (self.refresh_every and self._since_refresh + 1 >= self.refresh_every)
        with torch.no_grad():
            if refresh and self._graphed_refresh():
                # the pillar net runs inside the refresh's CUDA graph: its time counts in ms_backbone
                m2 = self._mark()
                features = self._refresh_features(upd.active)
                out = self.delta.refresh(self._every_site(), features, check=False)
                pfn_points = pfn_points_full = self._pfn_points
                self._since_refresh = 0
            elif refresh:
                pillars = self.stream.pillars(upd.active, check=False)
                feats = self._pfn(pillars)
                pfn_points = pfn_points_full = pillars.num_points.sum()
                m2 = self._mark()
                out = self._refresh(pillars, feats)
                self._since_refresh = 0
            else:
                # the PFN on every changed pillar, the emptied ones included (zero points: their rows
                # are ignored by the update, or zero in the dense mode), so that nothing waits for the
                # device to pick them out
                # dense: an emptied pillar stays a site, its input back to zero
                removed = torch.zeros_like(upd.removed) if self.dense else upd.removed
                pfn_points_full = self.stream.num_points
                if self.delta.cuda_graph and not self.profile:
                    # the pillar net runs inside the backbone's CUDA graph: its time counts in ms_backbone
                    m2 = self._mark()
                    out = self.delta.update(upd.changed[:, 1:], self._changed_features, removed, check=False)
                    pfn_points = self._pfn_points
                else:
                    changed = self.stream.pillars(upd.changed, check=False)
                    feats = self._pfn(changed)
                    pfn_points = changed.num_points.sum()
                    m2 = self._mark()
                    out = self.delta.update(changed.coords[:, 1:], feats, removed, profile=self.profile,
                                            check=False)
                self._since_refresh += 1
            st.guard = self._check_state(refresh)
            if st.guard and refresh:  # nothing to recycle from: the input or the weights are not finite
                st.guard += " after a full recomputation: the pillar features or the weights hold NaN or inf"
            elif st.guard:  # recompute everything from the window, within this step
                pillars = self.stream.pillars(upd.active, check=False)
                feats = self._pfn(pillars)
                pfn_points = pfn_points + pillars.num_points.sum()
                out = self._refresh(pillars, feats)
                self._since_refresh = 0
                st.guard_refreshes += 1
                refresh = True
                if self._check_state(True):
                    st.guard += ("; the full recomputation is not finite either: the pillar features or the "
                                 "weights hold NaN or inf")
        if self.detector is not None:
            self._note_head_sites(refresh)
        m3 = self._mark()
        if self.device.type == "cuda":
            m3.synchronize()
        st.pfn_points, st.pfn_points_full = int(pfn_points), int(pfn_points_full)
        st.refreshed = bool(refresh)
        st.ms_stream, st.ms_pfn, st.ms_backbone = self._elapsed(m0, m1), self._elapsed(m1, m2), self._elapsed(m2, m3)
        st.layers = [LayerStats(s.name, s.active, s.changed, s.touched, s.ms) for s in self.delta.stats]
        st.state_max = self.delta.state_max
        self.stats = st
        return out

    def _refresh(self, pillars, feats: Tensor) -> Tensor:
        """Every layer recomputed from the window's pillars; in the dense mode from every site of the grid."""
        if not self.dense:  # the stream's active pillars: inside the grid, each once, int32
            return self.delta.refresh(pillars.coords[:, 1:], feats, check=False)
        full = self._on_grid(pillars.coords, feats)
        return self.delta.refresh(self._every_site(), full, check=False)  # every site once, int32, by construction

    def _on_grid(self, coords: Tensor, feats: Tensor) -> Tensor:
        """The pillars' features (P, C) at their sites of the grid, (H * W, C), zero elsewhere; rows whose coords
        are (0, -1, -1) (a graph's padding) land in a scratch row past the grid."""
        H, W = self.grid.shape
        keys = torch.where(coords[:, 1] >= 0, coords[:, 1].long() * W + coords[:, 2].long(), H * W)
        full = feats.new_zeros(H * W + 1, feats.shape[1])
        full[keys] = feats
        return full[:H * W]

    def _every_site(self) -> Tensor:
        if self._all_sites is None:
            H, W = self.grid.shape
            yy, xx = torch.meshgrid(torch.arange(H, device=self.device), torch.arange(W, device=self.device),
                                    indexing="ij")
            self._all_sites = torch.stack([yy.reshape(-1), xx.reshape(-1)], 1).to(torch.int32)
        return self._all_sites

    def _graphed_refresh(self) -> bool:
        """Whether a refresh runs the pillar net inside the backbone's CUDA graph of the refresh (dense mode)."""
        return bool(self.dense and self.delta.cuda_graph and not self.profile and delta_module.REFRESH_CUDA_GRAPH
                    and self.device.type == "cuda")

    def _refresh_features(self, active: Tensor, cap: Optional[int] = None):
        """The features function of a graphed refresh: the window's active pillars ``(P, 3)`` go into a list padded
        to a power-of-two capacity (one graph per capacity; ``cap``, else the smallest from 1024 that holds them);
        the function gives the pillar net's features of every site of the grid (zero where no pillar is) and
        counts their points in ``_pfn_points``."""
        n = active.shape[0]
        cap = cap or graph_capacity(n, 1024)
        if cap not in self._refresh_inputs:
            coords = torch.full((cap, 3), -1, dtype=torch.int32, device=self.device)
            coords[:, 0] = 0  # padding rows (0, -1, -1): the stream's gather gives them no points
            self._refresh_inputs[cap] = (coords, functools.partial(self._features_of_every_site, coords))
        coords, fn = self._refresh_inputs[cap]
        coords[n:, 1:].fill_(-1)
        coords[:n].copy_(active)
        return fn

    def warm_up(self, pillars: Optional[int] = None, points: int = 16384) -> int:
        """Record now, before the first step, the CUDA graphs a stream records the first time it meets a size: the
        refresh for every capacity up to ``pillars`` pillars in the window (default: the stream's ``max_pillars``),
        the update for every capacity of up to as many changed pillars, :meth:`detect`'s, and the stream's push for
        slices of up to ``points`` points (:meth:`PillarStream.warm_up`). A step that records
        one takes several milliseconds more, once per size; after ``warm_up()`` none does below ``pillars``. The
        graphs' memory is held as long as the model, and grows with ``pillars`` (each refresh graph keeps its own,
        with the pillar net's activations for its capacity): give the most pillars you expect a window to hold.
        Returns how many graphs it recorded: 0 on the CPU and when there is nothing to record."""
        if self._since_refresh is not None:
            raise ValueError("warm_up() must come before the first step (or right after reset())")
        if pillars is None:
            pillars = self.stream.max_pillars
        if isinstance(pillars, bool) or not isinstance(pillars, int) or pillars < 1:
            raise ValueError(f"pillars must be an int >= 1, got {pillars!r}")
        if isinstance(points, bool) or not isinstance(points, int) or points < 0:
            raise ValueError(f"points must be an int >= 0, got {points!r}")
        top = graph_capacity(pillars, 1)
        recorded = 0
        with torch.no_grad():
            if self._graphed_refresh():  # refreshes of the empty window: the first step recomputes everything
                empty = self.stream.active_coords()[:0]
                known = self.delta.cuda_graphs
                for cap in (1 << k for k in range(10, max(top, 1024).bit_length())):
                    self.delta.refresh(self._every_site(), self._refresh_features(empty, cap), check=False)
                recorded += self.delta.cuda_graphs - known
            if self.delta.cuda_graph and not self.profile and self.device.type == "cuda":
                for cap in (1 << k for k in range(8, max(top, 256).bit_length())):
                    recorded += self.delta.prepare_update(cap, self._changed_features)
            if self.detector is not None and self.device.type == "cuda":
                known = self._detect_graph
                self.detect()
                recorded += self._detect_graph is not known
            recorded += self.stream.warm_up(points)
        self._head = self._head_sites = None
        self.stats = StepStats()
        return recorded

    def _features_of_every_site(self, coords: Tensor, sites: Tensor) -> Tensor:
        pillars = self.stream.pillars(coords, check=False)
        self._pfn_points.copy_(pillars.num_points.sum())
        return self._on_grid(coords, self._pfn(pillars))

    def _note_head_sites(self, refreshed: bool) -> None:
        """After a step: the output sites it changed, for the head (a refresh, or a step whose site lists are
        padded on the device, makes the head recompute everything)."""
        if refreshed or self.delta.sync_free or self._head_sites is None:
            self._head_sites = None
            return
        for change in self.delta.up_changes:
            self._head_sites += [change.sites, change.added, change.removed]

    def head_outputs(self) -> dict:
        """The detector's head (1x1 convolutions) on the recycled BEV map: ``cls_preds``, ``box_preds`` (and
        ``dir_cls_preds``) as ``dense_head`` gives them, recomputed only at the output sites that changed since
        the last call (all of them after a refresh, on CUDA, where the step's site lists stay on the device, and
        once :data:`HEAD_DENSE_SHARE` of the sites changed).
        The maps are kept: valid until the next call."""
        if self.detector is None:
            raise ValueError("detect() needs a model made by SSCATeRPointPillars.from_detector(detector)")
        head = self.detector.dense_head
        dtype = head.conv_cls.weight.dtype
        with torch.no_grad():
            dense = self._head is None or self._head_sites is None
            if not dense and self._head_sites:
                H, W = self.delta.out.shape[2:]
                changed = torch.zeros(H * W, dtype=torch.bool, device=self.device)  # each site once, no sort
                changed[torch.cat(self._head_sites).long() @ torch.tensor([W, 1], device=self.device)] = True
                keys = torch.nonzero(changed).view(-1)
                dense = keys.numel() >= HEAD_DENSE_SHARE * H * W  # one dense convolution beats gathering most rows
            if dense:
                self._head = head(self.delta.out.to(dtype))
            elif self._head_sites:
                ys, xs = keys // W, keys % W
                # (n, C): the changed sites' features, rows of the channels-last map
                feats = self.delta.out[0].permute(1, 2, 0)[ys, xs].to(dtype)
                convs = {"cls_preds": head.conv_cls, "box_preds": head.conv_box, "dir_cls_preds": head.conv_dir_cls}
                for key, conv in convs.items():
                    if conv is not None:
                        self._head[key][0, ys, xs] = F.linear(feats, conv.weight.view(conv.out_channels, -1),
                                                              conv.bias)
        self._head_sites = []
        return self._head

    def detect(self) -> dict:
        """Boxes of the current window (after :meth:`step`): the detector's head on the recycled BEV map
        (:meth:`head_outputs`: at the sites that changed), its decode and post-processing (:meth:`from_detector`
        models only). One dict of ``boxes (K, 7)``, ``scores (K,)``, ``labels (K,)`` (1-based into the
        detector's ``class_names``), as ``detector.predict`` gives."""
        from lidarops.models.pointpillars import PointPillars
        if (DETECT_CUDA_GRAPH and self.device.type == "cuda" and self.delta.sync_free and self.detector is not None
                and type(self.detector).postprocess is PointPillars.postprocess):
            return self._detect_replay()
        raw = self.head_outputs()
        with torch.no_grad():
            return self.detector.postprocess(raw)[0]

    def _detect_replay(self) -> dict:
        """:meth:`detect` as one CUDA graph (:data:`DETECT_CUDA_GRAPH`): the dense head on the output map, the
        decode and :func:`~lidarops.models.postprocess.postprocess_padded` (the boxes ``postprocess`` keeps, in
        its order). Captured on first use, and again when TF32 or autocast change (the graph keeps the kernels
        chosen under them)."""
        flags = (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32,
                 torch.is_autocast_enabled("cuda"))
        graphed = self._detect_graph
        # the graph holds the config's thresholds: a change of the detector's config records it again
        if graphed is None or graphed[0] != flags or graphed[1] != self.detector.config:
            self._detect_graph = (flags, copy.deepcopy(self.detector.config), *self._capture_detect())
        _, _, graph, raw, out = self._detect_graph
        graph.replay()
        self._head, self._head_sites = raw, []
        n, bad = out["read"].tolist()  # the one host read
        if bad and value_checks_enabled():  # the eager post-processing names the bad box
            with torch.no_grad():
                return self.detector.postprocess(raw)[0]
        # copies: the graph's outputs are overwritten by the next replay
        return {k: out[k][0, :n].clone() for k in ("boxes", "scores", "labels")}

    def _capture_detect(self) -> tuple:
        from lidarops.models.cuda_graph import _bad_boxes, _decode_candidates
        from lidarops.models.postprocess import postprocess_padded
        head, cfg = self.detector.dense_head, self.detector.config
        dtype = head.conv_cls.weight.dtype

        def body():
            raw = head(self.delta.out.to(dtype))
            # only the anchors the NMS can visit are decoded, as in the detector's own graph; the eager
            # post-processing's value checks come back as a flag read with the count (a graph cannot raise)
            decoded, bad = _decode_candidates(head, raw, cfg)
            out = postprocess_padded(*decoded, cfg)
            bad = _bad_boxes(*decoded, cfg) if bad is None else bad
            out["read"] = torch.stack([out["count"][0], bad[0].to(out["count"].dtype)])
            return raw, out

        with torch.no_grad(), validation(False), uncached_autocast():
            graph, (raw, out) = record_graph(body, self.device)
        return graph, raw, out

    def window_points(self) -> Tensor:
        """The points the stream holds (x, y, z, intensity), pillar by pillar in key order, each pillar's in time
        order: what the detector must see to equal the stream (``detector.predict`` on them voxelizes the same
        pillars with the same points in the same slots)."""
        pillars = self.stream.pillars()
        n = pillars.features.shape[1]
        keep = torch.arange(n, device=pillars.features.device) < pillars.num_points[:, None].long()
        return pillars.features[:, :, :4][keep]

    @classmethod
    def from_detector(cls, detector, window: float = 0.1, refresh_every: int = 25, dtype: torch.dtype = torch.float32,
                      device=None, **kwargs) -> "SSCATeRPointPillars":
        """Streaming detection with a trained PointPillars (``backbone_mode="dense"``): its grid, its own pillar net
        (:class:`DetectorPFN`) on the pillars that changed, its backbone recycled over every site (``dense=True``)
        and, by :meth:`detect`, its head and post-processing. Each step's boxes equal ``detector.predict`` on
        :meth:`window_points` (float rounding aside: the recycled sums add in another order). On CUDA compare with
        TF32 off (``torch.backends.cudnn.allow_tf32 = False``, on by default): the recycled layers always sum in
        float32, while the pillar net, the head and the detector follow torch's flags.

        The stream holds the detector's ``MAX_POINTS_PER_VOXEL`` points per pillar and ``MAX_NUMBER_OF_VOXELS``
        (test) pillars, dropping what does not fit (``overflow="drop"``, the stream's rule), unless given.
        """
        from lidarops.models.pointpillars import PointPillars
        from lidarops.stream import PillarGrid

        if not isinstance(detector, PointPillars):
            raise TypeError(f"detector must be a PointPillars, got {type(detector).__name__}")
        cfg = detector.config
        if cfg.backbone_mode != "dense":
            raise ValueError(f"from_detector needs a detector with backbone_mode='dense', got {cfg.backbone_mode!r}")
        detector.eval()
        grid = PillarGrid(cfg.point_cloud_range, cfg.voxel_size)
        kwargs.setdefault("max_points_per_pillar", cfg.max_points_per_voxel)
        kwargs.setdefault("max_pillars", cfg.max_voxels_test)
        kwargs.setdefault("overflow", "drop")
        pfn = DetectorPFN(detector.vfe, kwargs["max_points_per_pillar"]).eval()
        model = cls(pfn, detector.backbone_2d, grid, window, refresh_every=refresh_every, dtype=dtype, device=device,
                    dense=True, **kwargs)
        model.detector = detector
        return model

    def _check_state(self, refreshed: bool) -> str:
        """The guard, on the host (``state_max`` came with the step's figures): why the state must be
        recomputed, or "". After a refresh it restarts the peak and reports only a non-finite state."""
        m = self.delta.state_max
        if m is None:
            return ""
        if not math.isfinite(m):
            self._state_peak = self._state_prev = 0.0
            return f"max |acc| is {m}: an accumulator holds NaN or inf"
        if refreshed or m == 0:  # exact zeros (an empty window) hold no rounding residue either
            self._state_peak = self._state_prev = m
            return ""
        r, prev, peak = self.guard_ratio, self._state_prev, max(self._state_peak, m)
        self._state_peak, self._state_prev = peak, m
        if prev > 0 and m > r * prev:
            return (f"max |acc| jumped from {prev:.3g} to {m:.3g} in one step (more than {r:g}x): a huge value "
                    "entered or the state was corrupted")
        if peak > r * m:
            return (f"max |acc| fell from {peak:.3g} to {m:.3g} since the last refresh (more than {r:g}x): what "
                    "left would leave float rounding residue behind")
        return ""

    def recompute(self, points: Tensor, max_points_per_pillar: Optional[int] = None,
                  max_pillars: Optional[int] = None) -> Tensor:
        """The full recomputation SSCATeR must equal: ``pillarize`` the window's points, run the PFN on
        every pillar and ``backbone(mode="sparse")``. ``points (Tensor[n, 4])`` = the current window
        (with ``overflow="drop"``: the points the stream kept)."""
        from lidarops.sparse import SparseConvTensor
        from lidarops.stream import pillarize
        p = pillarize(points.to(self.device), self.grid,
                      max_points_per_pillar or self.stream.max_points_per_pillar, max_pillars or self.stream.max_pillars)
        with torch.no_grad():
            f = self.pfn(p)
            x = SparseConvTensor(f.to(self.backbone.blocks[0][1].weight.dtype), p.coords, list(self.grid.shape), 1)
            return self.backbone(x, mode="sparse")

