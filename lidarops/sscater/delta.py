"""SSCATeR's recycling backbone: a BEV backbone whose every convolution keeps its output and
updates it by ``acc += (I_curr - I_prev) (*) W`` on the changed sites only (Hunt et al., SSCATeR,
equation 2), with change maps propagated through BatchNorm/ReLU, strided and transposed convolutions
(Algorithm 1).

State (all dense, channels last, on the backbone's device):

- per node (the pillar map, each block's sites, each upsampling branch's sites): an ``active`` map,
  which is the sparse network's site set (pillars with points; a strided convolution's outputs with an
  active input under the kernel, tracked by a ``cover`` count; the children of active inputs after a
  transposed convolution; submanifold layers keep their block's sites);
- per convolution: ``acc`` (Ho, Wo, Cout), the convolution without bias of the layer's zero-filled
  input, kept up to date at the *active* output sites (linear in the input, so a delta at a few sites
  updates it exactly), and the layer's post-activation output ``feats`` (zero at inactive sites), the
  next layer's input. The upsampling layers write their outputs straight into the returned
  (1, 384, H/2, W/2) map.

One step: the changed input sites carry ``delta = new - old``; each layer first updates its active
map from the sites that became active or inactive, scatters ``delta (*) W`` into ``acc`` at the active
sites it reaches (per tap: gather, GEMM, scatter-add; :func:`torch.ops.lidarops.sscater_scatter_`),
computes ``acc`` in full at the sites that just became active (their ``acc`` was not maintained while
inactive; ``sscater_gather_``), and re-evaluates BatchNorm (folded) and ReLU only at the sites the
scatter reached or whose status changed (``sscater_touch_`` lists them once each through a stamp map,
``sscater_finalize_compact_`` evaluates them and compacts the changed ones). A layer is a handful of
kernels: site lists are padded to upper bounds with (-1, -1) rows instead of being compacted on the
host, and the statistics of a step are read once at its end. On CUDA (``sync_free``) the lists are
never trimmed: every list holds each site of its grid at most once, and the scatter and gather read
their row counts from the device, so a step makes no host synchronisation between layers; on CPU one
synchronisation per layer (free there) trims them.
The changed sites it passes on are those whose post-ReLU value changed (a site that stays <= 0 is not
passed on) plus those whose active status changed.

State check: every layer's ``acc`` is a view of one flat buffer, so after each refresh and update one
reduction gives ``state_max`` = max |acc| over all accumulators (NaN or inf when one is not finite),
read with the step's figures (no extra host synchronisation). ``SSCATeRPointPillars`` refreshes the
state when it is not finite or when its magnitude swings (its guard; docs/sscater.md).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional, Protocol, Sequence, runtime_checkable

import torch
from torch import Tensor

from lidarops._cuda_graphs import graph_capacity, record_graph, uncached_autocast

__all__ = [
    "CHANNEL_SPARSE", "DENSE_CHANNELS_LAST", "DENSE_REFRESH", "REFRESH_CUDA_GRAPH", "Change", "DeltaBackbone",
    "LayerStats", "DeltaLayer",
]

# Share of zero delta values from which the channel-sparse scatter beats the per-tap GEMM, by device type
# (measured by benchmarks/bm_sscater.py --only channel_sparse; docs/sscater.md). Above 1: never, as on the
# H200, where the tiled GEMM wins below 95 % zeros and the choice made on the device costs launches.
CHANNEL_SPARSE = {"cpu": 0.85, "cuda": 2.0}
# Share of the grid's sites given to a refresh from which it runs dense convolutions instead of sparse ones, by
# device type (above 1: never).
DENSE_REFRESH = {"cpu": 0.5, "cuda": 0.5}
# The dense refresh's convolutions on the maps' own channels-last memory (True), or on NCHW copies, by device type.
DENSE_CHANNELS_LAST = {"cpu": True, "cuda": False}
# With cuda_graph, a refresh of every site of the grid replays a CUDA graph of the whole refresh: eager, its
# hundred-odd launches, not its convolutions, set its time. Each graph (one per features function: for
# SSCATeRPointPillars one per pillar capacity) keeps its own memory for the refresh's intermediate maps.
REFRESH_CUDA_GRAPH = True


@runtime_checkable
class DeltaLayer(Protocol):
    """What :class:`DeltaBackbone` reads of one convolution of a BEV backbone (a PointPillars
    ``BaseBEVBackbone``: :meth:`lidarops.models.BaseBEVBackbone.delta_layers` lists its own).

    Attributes:
        kind (str): ``"down"`` (strided 3x3, padding 1: a regular sparse convolution, the first of a
            block), ``"subm"`` (3x3 submanifold, the rest of the block) or ``"up"`` (transposed, kernel =
            stride: each input site feeds its stride^2 children; one per block, after the blocks).
        block (int): the block the layer belongs to (for ``"up"``: the block it upsamples).
        stride (int): the convolution's stride.

    ``sparse_weight()`` is the weight in :mod:`lidarops.sparse`'s layout ``[Cout, kh, kw, Cin]`` and
    ``folded_norm()`` the eval-mode BatchNorm after it as ``(scale, shift)``: ``y = relu(x * scale +
    shift)``; both are read again by :meth:`DeltaBackbone.reload`. Layers come in execution order: each
    block's ``down`` then its ``subm`` layers, then the ``up`` layers.
    """

    kind: str
    block: int
    stride: int

    def sparse_weight(self) -> Tensor: ...

    def folded_norm(self) -> tuple[Tensor, Tensor]: ...


@dataclass
class Change:
    """What changed at one node in one step.

    Attributes:
        sites (Tensor[n, 2] int32): (y, x) of the sites whose value changed; (-1, -1) rows are padding.
        delta (Tensor[n, C]): new value - old value at those sites.
        added, removed (Tensor[a, 2] / [r, 2] int32): sites that became active / inactive (padded too).
        count (Tensor[1] int64, optional): only the first ``count[0]`` rows of ``sites`` / ``delta`` are
            used (a length known only on the device: the sync-free step does not trim its lists).
        added_count (Tensor[1] int64, optional): the same for ``added``.
    """

    sites: Tensor
    delta: Tensor
    added: Tensor
    removed: Tensor
    count: Optional[Tensor] = None
    added_count: Optional[Tensor] = None


@dataclass
class LayerStats:
    """Per-layer figures of the last step: ``active`` sites, ``changed`` sites passed on, ``touched``
    sites re-evaluated, ``ms`` (wall time, synchronised on CUDA when profiling)."""

    name: str
    active: int = 0
    changed: int = 0
    touched: int = 0
    ms: float = 0.0


class _Layer:
    def __init__(self, spec: DeltaLayer, dtype, device, in_shape, out_shape, name: str):
        self.kind, self.block, self.name = spec.kind, spec.block, name
        self.stride = spec.stride if spec.kind != "subm" else 1
        self.padding = 0 if spec.kind == "up" else 1
        self.transposed = spec.kind == "up"
        w = spec.sparse_weight().detach().to(device=device, dtype=dtype)
        # (Cout, kh, kw, Cin) view of tap-major memory: the scatter op's GEMMs read it in place
        self.weight = w.permute(1, 2, 0, 3).contiguous().permute(2, 0, 1, 3)
        self.weight_flat = w.reshape(w.shape[0], -1).contiguous()  # (Cout, kh * kw * Cin) for the gather
        # torch's layout for a dense refresh (conv2d: (Cout, Cin, kh, kw); conv_transpose2d: (Cin, Cout, kh, kw)),
        # in the memory format _dense_conv runs in on this device
        self.weight_dense = (w.permute(3, 0, 1, 2) if self.transposed else w.permute(0, 3, 1, 2)).contiguous(
            memory_format=_dense_format(torch.device(device)))
        self.input: Optional[Tensor] = None  # the input node's features (H_in, W_in, Cin)
        self.kh, self.kw = w.shape[1], w.shape[2]
        scale, shift = spec.folded_norm()
        self.scale = scale.detach().to(device=device, dtype=dtype).contiguous()
        self.shift = shift.detach().to(device=device, dtype=dtype).contiguous()
        self.in_shape, self.out_shape = tuple(in_shape), tuple(out_shape)
        self.cin, self.cout = w.shape[3], w.shape[0]
        self.acc = torch.zeros(*out_shape, self.cout, dtype=dtype, device=device)
        self.feats: Optional[Tensor] = None  # set by the owner (own buffer or a view of the output map)
        self.active: Optional[Tensor] = None
        # sites touched in a step (zeroed at the start of each step; a view of DeltaBackbone._stamps)
        self.stamp: Optional[Tensor] = None
        self.stats = LayerStats(name)


def _keys(sites: Tensor, W: int) -> Tensor:
    return sites[:, 0].long() * W + sites[:, 1].long()


class DeltaBackbone:
    """Recycling state of a BEV backbone's convolutions on one (H, W) pillar grid (batch 1, eval mode).

    Args:
        layers (sequence of DeltaLayer, or a backbone with ``delta_layers()``): the convolutions in
            execution order (see :class:`DeltaLayer`); their weights and BatchNorm running statistics are
            copied (folded) at construction; call :meth:`reload` after changing them. A backbone module
            (e.g. :class:`lidarops.models.BaseBEVBackbone`) must be in eval mode.
        shape (tuple[int, int]): the pillar grid (H, W).
        dtype (torch.dtype): float32 or float64 state.
        device: where the state lives (default: the layers' weights').
        sync_free (bool): never trim the site lists on the host; each op reads the previous op's row
            count from the device instead, so a step makes no host synchronisation between layers
            (default: on CUDA, where a sync stalls the launch queue; on CPU reading a count is free
            and trimmed lists are smaller).
        cuda_graph (bool): run :meth:`update` as a CUDA graph (one per power-of-two input capacity,
            captured on first use); default: on CUDA with ``sync_free``. Not with ``profile=True``.
        state_check (bool): after every refresh and update, measure ``state_max`` (max |acc| over every
            accumulator; NaN or inf if one is not finite): one reduction over the accumulators, read
            with the step's figures. Default on; ``state_max`` is None when off.
        channel_sparse (float, optional): the share of exactly-zero delta values from which a layer's
            scatter multiplies each changed site's nonzero channels alone instead of running the per-tap GEMM
            (``sscater_scatter_``'s argument; 0: always, above 1: never). Default: the device's measured
            crossover (:data:`CHANNEL_SPARSE`). Read at each step (a CUDA graph keeps the value it was
            captured with).

    ``refresh(sites, features)`` sets the whole input (a full recomputation, no recycling);
    ``update(change)`` applies one step's input change; both return the (1, C_out, H/2, W/2) map, which
    is the state itself: it is overwritten by the next call (clone it to keep it). Its memory format is
    ``torch.channels_last`` (call ``.contiguous()`` for channels-first memory).
    """

    def __init__(self, layers: "Sequence[DeltaLayer]", shape, dtype: torch.dtype = torch.float32, device=None,
                 sync_free: Optional[bool] = None, cuda_graph: Optional[bool] = None, state_check: bool = True,
                 channel_sparse: Optional[float] = None):
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self._layer_source = self._as_layer_source(layers)
        first = self._layer_source()[0].sparse_weight()
        self.shape = (int(shape[0]), int(shape[1]))
        self.dtype = dtype
        self.device = torch.device(device) if device is not None else first.device
        self.sync_free = self.device.type == "cuda" if sync_free is None else bool(sync_free)
        self.cuda_graph = self.sync_free and self.device.type == "cuda" if cuda_graph is None else bool(cuda_graph)
        if self.cuda_graph and not (self.sync_free and self.device.type == "cuda"):
            raise ValueError(f"cuda_graph needs a CUDA device and sync_free=True, got {self.device} and "
                             f"sync_free={self.sync_free}")
        self.state_check = bool(state_check)
        if channel_sparse is None:
            channel_sparse = CHANNEL_SPARSE.get(self.device.type, 0.85)
        if isinstance(channel_sparse, bool) or not isinstance(channel_sparse, (int, float)) \
                or channel_sparse != channel_sparse:
            raise ValueError(f"channel_sparse must be a number (a share of zero delta values), got {channel_sparse!r}")
        self.channel_sparse = float(channel_sparse)
        self.reload()

    # ---- construction ----------------------------------------------------------------------------

    @staticmethod
    def _as_layer_source(layers):
        """A function giving the current layer list: a backbone's ``delta_layers`` (re-read on reload, and
        its eval mode checked), or the given list."""
        if hasattr(layers, "delta_layers"):
            if getattr(layers, "training", False):
                raise ValueError("the backbone must be in eval mode (SSCATeR folds BatchNorm's running statistics)")
            return layers.delta_layers
        layers = list(layers)
        kinds = [getattr(layer, "kind", None) for layer in layers]
        if not layers or not all(isinstance(layer, DeltaLayer) for layer in layers) \
                or not set(kinds) <= {"down", "subm", "up"} or "down" not in kinds or "up" not in kinds:
            raise ValueError("layers must be a backbone with delta_layers() or a list of DeltaLayer (kind 'down', "
                             f"'subm' or 'up', block, stride, sparse_weight(), folded_norm()), got kinds {kinds}")
        return lambda: layers

    def reload(self) -> None:
        """(Re)build the state from the layers' current parameters; the state is cleared."""
        dev, dt = self.device, self.dtype
        specs = list(self._layer_source())
        H, W = self.shape
        self.in_channels = int(specs[0].sparse_weight().shape[3])
        # the input maps, flat with one scratch row at H * W where padding rows of a step's input land
        self._in_feats = torch.zeros(H * W + 1, self.in_channels, dtype=dt, device=dev)
        self._in_active = torch.zeros(H * W + 1, dtype=torch.bool, device=dev)
        self.in_feats = self._in_feats[:H * W].view(H, W, self.in_channels)
        self.in_active = self._in_active[:H * W].view(H, W)
        self._graphs: dict = {}  # CUDA graphs of the step, by input capacity
        self._nchw: dict = {}  # the dense refresh's NCHW copies of the features, by shape
        self._refresh_graphs: dict = {}  # refreshes of every site as CUDA graphs, by features function
        self.layers: list[_Layer] = []
        block_shape, block_active, self.block_cover = {}, {}, {}
        shape = (H, W)
        ups = [s for s in specs if s.kind == "up"]
        for spec in specs:
            if spec.kind == "up":
                continue
            if spec.kind == "down":
                s = spec.stride
                out = ((shape[0] + 2 - 3) // s + 1, (shape[1] + 2 - 3) // s + 1)
                block_active[spec.block] = torch.zeros(out, dtype=torch.bool, device=dev)
                self.block_cover[spec.block] = torch.zeros(out, dtype=torch.int32, device=dev)
                block_shape[spec.block] = out
            else:
                out = shape
            name = f"block{spec.block}.{'down' if spec.kind == 'down' else 'subm'}{len(self.layers)}"
            layer = _Layer(spec, dt, dev, shape, out, name)
            layer.feats = torch.zeros(*out, layer.cout, dtype=dt, device=dev)
            layer.active = block_active[spec.block]
            layer.input = self.layers[-1].feats if self.layers else self.in_feats
            self.layers.append(layer)
            shape = out
        self.block_last = {}
        for i, layer in enumerate(self.layers):
            self.block_last[layer.block] = i
        up_shapes = [(block_shape[s.block][0] * s.stride, block_shape[s.block][1] * s.stride) for s in ups]
        if len(set(up_shapes)) != 1:
            raise ValueError(f"the upsampling branches reach different grids {up_shapes}")
        Hu, Wu = up_shapes[0]
        couts = [int(s.sparse_weight().shape[0]) for s in ups]
        # channels_last memory: each upsampling layer writes its sites' channels contiguously
        self.out = torch.zeros(1, sum(couts), Hu, Wu, dtype=dt, device=dev).to(memory_format=torch.channels_last)
        self.up_layers: list[_Layer] = []
        c0 = 0
        for spec, cu in zip(ups, couts):
            layer = _Layer(spec, dt, dev, block_shape[spec.block], (Hu, Wu), f"up{spec.block}")
            layer.input = self.layers[self.block_last[spec.block]].feats
            layer.feats = self.out[0, c0:c0 + cu].permute(1, 2, 0)  # (Hu, Wu, Cu) view of channels-last memory
            layer.active = torch.zeros(Hu, Wu, dtype=torch.bool, device=dev)
            self.up_layers.append(layer)
            c0 += cu
        self.stats: list[LayerStats] = [layer.stats for layer in self.layers + self.up_layers]
        # every output site sees an input under the kernel (padding < kernel; a transposed layer's kernel at least
        # its stride): a full input makes every site of every layer active
        self._covering = all(lay.padding < min(lay.kh, lay.kw) for lay in self.layers) and all(
            lay.padding == 0 and min(lay.kh, lay.kw) >= lay.stride for lay in self.up_layers)
        self.steps = 0
        every = self.layers + self.up_layers
        # every layer's accumulator in one buffer: the state check is one reduction over it
        self._accs = torch.zeros(sum(lay.acc.numel() for lay in every), dtype=dt, device=dev)
        off = 0
        for lay in every:
            n = lay.acc.numel()
            lay.acc = self._accs[off:off + n].view(lay.acc.shape)
            off += n
        self.state_max: Optional[float] = 0.0 if self.state_check else None
        # every layer's stamp map in one buffer, zeroed once per step
        self._stamps = torch.zeros(sum(lay.out_shape[0] * lay.out_shape[1] for lay in every), dtype=torch.int32,
                                   device=dev)
        off = 0
        for lay in every:
            n = lay.out_shape[0] * lay.out_shape[1]
            lay.stamp = self._stamps[off:off + n].view(lay.out_shape)
            off += n

    # ---- full recomputation ----------------------------------------------------------------------

    def refresh(self, sites: Tensor, features, check: bool = True) -> Tensor:
        """Set the input to ``features (Tensor[P, Cin])`` at ``sites (Tensor[P, 2] int, (y, x))`` and
        recompute every layer's state from it (no recycling): with the sparse convolution ops, or with torch's
        dense convolutions when the device's :data:`DENSE_REFRESH` share of the grid's sites is given (half; a
        dense stream, such as ``SSCATeRPointPillars.from_detector``'s, lists every site). ``check=False`` is for
        input that is already right (int32 sites inside the grid, each once, features in the state's dtype on its
        device): no wait for the device to check it; ``features`` may then be a function of the sites giving
        them (``features(sites) -> Tensor[P, Cin]``), which a CUDA graph records. With ``cuda_graph``, a refresh
        given every site of the grid replays a CUDA graph of the whole refresh (one per features function,
        recorded by the first such refresh; :data:`REFRESH_CUDA_GRAPH`)."""
        if callable(features) and check:
            raise ValueError("features can be a function of the sites only with check=False")
        if check:
            sites, features = self._check_input(sites, features)
        H, W = self.shape
        dense = sites.shape[0] >= DENSE_REFRESH.get(self.device.type, 2.0) * H * W
        if REFRESH_CUDA_GRAPH and self.cuda_graph and dense and sites.shape[0] == H * W and self._covering:
            values = self._refresh_replay(sites, features)
        else:
            if callable(features):
                features = features(sites)
            values = self._refresh_body(sites, features, dense).tolist()
        for st, a in zip(self.stats, values):
            st.active = st.changed = st.touched = int(a)
        if self.state_check:
            self.state_max = values[-1]
        self.steps = 0
        return self.out

    def _refresh_body(self, sites: Tensor, features: Tensor, dense: bool) -> Tensor:
        """The refresh on checked input; returns its figures on the device (float64: each layer's active count,
        then ``state_max``), read at once: a wait for the device per layer would stall the launch queue."""
        H, W = self.shape
        self.in_feats.zero_()
        self.in_active.zero_()
        keys = _keys(sites, W)
        self.in_feats.view(H * W, -1)[keys] = features
        self.in_active.view(-1).index_fill_(0, keys, True)  # no host scalar: a CUDA graph records it
        # the state's dtype decides, not a caller's autocast: the steps' own ops do not autocast, and a refresh
        # in another precision would leave accumulators that the recycled updates no longer match
        with torch.autocast(self.device.type, enabled=False):
            if dense:
                self._refresh_dense(full=sites.shape[0] == H * W and self._covering)
            else:
                self._refresh_sparse(sites, features)
        figures = [layer.active.sum().to(torch.float64) for layer in self.layers + self.up_layers]  # exact
        if self.state_check:
            figures.append(self._state_max().to(torch.float64))
        return torch.stack(figures)

    def _refresh_replay(self, sites: Tensor, features) -> list:
        """A refresh of every site of the grid as a CUDA graph (its shapes are the grid's), one per features
        function (None: given as a tensor): the first runs eagerly, which also warms up the convolutions, and then
        records the graph, which the later ones replay. Returns the figures, read."""
        fn = features if callable(features) else None
        g = self._refresh_graphs.get(fn)
        if g is None:
            s_sites = sites.clone()
            s_feats = None if fn else features.clone()

            def body():
                return self._refresh_body(s_sites, fn(s_sites) if fn else s_feats, True)

            with uncached_autocast():  # the pillar net of fn may run under a caller's autocast
                values = body().tolist()
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph):  # recording runs nothing: the state stays this refresh's
                    figures = body()
            self._refresh_graphs[fn] = (s_sites, s_feats, graph, figures)
            return values
        s_sites, s_feats, graph, figures = g
        s_sites.copy_(sites)
        if s_feats is not None:
            s_feats.copy_(features)
        graph.replay()
        return figures.tolist()

    def _refresh_dense(self, full: bool) -> None:
        """The refresh by torch's dense convolutions over every site (most sites hold a pillar): the active maps
        from the input's by counting (strided layers) and spreading (transposed layers), each layer's acc the
        dense convolution of its input, zero at inactive sites, and its features from it. ``full``: every input
        site is active and every layer's kernels cover their outputs, so every site of every layer is active (no
        masks)."""
        F = torch.nn.functional
        # in NCHW each layer also writes its features in NCHW for the next convolution (no transposing copy), into
        # one buffer per shape (a layer's convolution has read its input before the layer writes there); each
        # block's upsampling layers run right after its last layer, while that layer's copy is current
        nchw = _dense_format(self.device) == torch.contiguous_format
        prev, x_nchw = self.in_active, None
        for i, layer in enumerate(self.layers):
            if layer.kind == "down":
                self._set_cover(layer, prev)
            out_nchw = self._nchw_buffer(layer) if nchw else None
            self._set_dense(layer, full, x_nchw, out_nchw)
            prev, x_nchw = layer.active, out_nchw
            if i != self.block_last[layer.block]:
                continue
            for up in self.up_layers:
                if up.block == layer.block:
                    ones = torch.ones(1, 1, up.kh, up.kw, dtype=self.dtype, device=self.device)
                    reached = F.conv_transpose2d(layer.active.to(self.dtype)[None, None], ones, stride=up.stride,
                                                 padding=up.padding)[0, 0]
                    up.active.copy_(reached > 0.5)
                    self._set_dense(up, full, out_nchw, None)

    def _nchw_buffer(self, layer: _Layer) -> Tensor:
        key = (layer.cout, *layer.out_shape)
        if key not in self._nchw:
            self._nchw[key] = torch.empty(layer.cout, *layer.out_shape, dtype=self.dtype, device=self.device)
        return self._nchw[key]

    def _set_cover(self, layer: _Layer, active_in: Tensor) -> None:
        """A strided layer's cover (active inputs under each output's kernel) and active map, from its input's
        active map (H_in, W_in) bool."""
        ones = torch.ones(1, 1, layer.kh, layer.kw, dtype=self.dtype, device=self.device)
        cover = torch.nn.functional.conv2d(active_in.to(self.dtype)[None, None], ones, stride=layer.stride,
                                           padding=layer.padding)[0, 0]
        self.block_cover[layer.block].copy_(cover.round().to(torch.int32))
        layer.active.copy_(self.block_cover[layer.block] > 0)

    def _set_dense(self, layer: _Layer, full: bool, x_nchw: Optional[Tensor], out_nchw: Optional[Tensor]) -> None:
        """The layer's acc and features (feats may be a view of the output map) from the dense convolution of its
        input (``x_nchw``: the input's NCHW copy, when the previous layer wrote one), in one pass over it."""
        torch.ops.lidarops.sscater_dense_finalize_(_dense_conv(layer, x_nchw), layer.acc, layer.feats, layer.scale,
                                                   layer.shift, None if full else layer.active, out_nchw)

    def _refresh_sparse(self, sites: Tensor, features: Tensor) -> None:
        """The refresh by the sparse convolution ops on the active sites."""
        from lidarops.sparse import SparseConvTensor
        from lidarops.sparse import functional as Fs
        x_sites, x_feats = sites, features
        block_out = {}
        for i, layer in enumerate(self.layers):
            x = SparseConvTensor(x_feats, _batch0(x_sites), list(layer.in_shape), 1)
            # acc = the regular convolution's outputs (the subm layer's padding keeps the grid)
            y = Fs.conv(x, layer.weight, None, "conv", stride=layer.stride, padding=layer.padding)
            layer.acc.zero_()
            layer.acc.view(-1, layer.cout)[_keys(y.indices[:, 1:], layer.out_shape[1])] = y.features
            if layer.kind == "down":
                act = torch.zeros(*layer.in_shape, dtype=torch.bool, device=self.device)
                act.view(-1)[_keys(x_sites, layer.in_shape[1])] = True
                self._set_cover(layer, act)
            # the regular convolution also reaches a subm layer's inactive neighbours: zero them, as a
            # step keeps them (their acc is set in full when they become active); the state check
            # then sees only the maintained sums
            layer.acc.masked_fill_(~layer.active[..., None], 0)
            x_sites = torch.nonzero(layer.active).int()
            x_feats = self._evaluate(layer, x_sites)
            block_out[layer.block] = (x_sites, x_feats)
        for layer in self.up_layers:
            src_sites, src_feats = block_out[layer.block]
            x = SparseConvTensor(src_feats, _batch0(src_sites), list(layer.in_shape), 1)
            y = Fs.conv(x, layer.weight, None, "transposed", stride=layer.stride)
            layer.acc.zero_()
            layer.active.zero_()
            if y.indices.shape[0]:
                k = _keys(y.indices[:, 1:], layer.out_shape[1])
                layer.acc.view(-1, layer.cout)[k] = y.features
                layer.active.view(-1)[k] = True
            self._evaluate(layer, torch.nonzero(layer.active).int())

    def _evaluate(self, layer: _Layer, sites: Tensor) -> Tensor:
        """feats = relu(acc * scale + shift) on the active sites, zero elsewhere; returns the values."""
        layer.feats.zero_()
        if sites.shape[0] == 0:
            return layer.acc.new_zeros(0, layer.cout)
        k = _keys(sites, layer.out_shape[1])
        v = torch.relu(layer.acc.view(-1, layer.cout)[k] * layer.scale + layer.shift)
        layer.feats[sites[:, 0].long(), sites[:, 1].long()] = v
        return v

    # ---- recycling step --------------------------------------------------------------------------

    def update(self, sites: Tensor, features: Tensor, removed: Tensor, profile: bool = False,
               check: bool = True) -> Tensor:
        """Apply one step's input change and return the output map.

        Args:
            sites (Tensor[n, 2] int): (y, x) of the pillars that changed (gained or lost points), each
                at most once.
            features (Tensor[n, Cin] or callable): their new features (ignored where ``removed``); or, with
                ``check=False``, a function of the sites giving them (``features(sites) -> Tensor[n, Cin]``),
                which a CUDA graph step records inside its graph (it then gets the sites padded with
                ``(-1, -1)`` rows, whose features are ignored; it must not synchronise with the host).
            removed (Tensor[n] bool): pillars that became empty (inactive).
            profile (bool): time each layer (synchronises CUDA after each layer; no CUDA graph).
            check (bool): validate and convert the input (which reads the sites on the host). ``False``
                is for input that is already right (int32 sites inside the grid, each once, features in
                the state's dtype, everything on its device, e.g. from a :class:`~lidarops.stream.PillarStream`):
                the step then makes no host synchronisation before its figures are read.
        """
        if callable(features) and check:
            raise ValueError("features can be a function of the sites only with check=False")
        if callable(features) and not (self.cuda_graph and not profile):
            features = features(sites)
        if check:
            sites, features = self._check_input(sites, features, finite=True)
            if removed.shape != (sites.shape[0],) or removed.dtype != torch.bool:
                raise ValueError(f"removed must be bool ({sites.shape[0]},), got {removed.dtype} "
                                 f"{tuple(removed.shape)}")
            removed = removed.to(self.device)
        if self.cuda_graph and not profile:
            active, counts = self._replay(sites, features, removed)
        else:
            active, counts = self._step(sites, features, removed, profile)
        figures = torch.cat([active[:, None], counts[:, 1:]], 1)
        if self.state_check:  # exact in float64: the counts are far below 2^53
            values = torch.cat([figures.flatten().to(torch.float64), self._state_max().view(1).to(torch.float64)])
            values = values.tolist()  # the step's one device-to-host copy
            self.state_max = values.pop()
            figures = [values[i:i + 3] for i in range(0, len(values), 3)]
        else:
            figures = figures.tolist()  # the step's one device-to-host copy
        for st, (a, changed, touched) in zip(self.stats, figures):
            st.active, st.changed, st.touched = int(a), int(changed), int(touched)
            if self.cuda_graph and not profile:
                st.ms = 0.0  # not timed per layer inside a graph
        self.steps += 1
        return self.out

    def _step(self, sites: Tensor, features: Tensor, removed: Tensor, profile: bool = False) -> tuple[Tensor, Tensor]:
        """The step on validated input; returns the active sites and the counts of every layer (on the
        device). With ``sync_free`` it makes no host synchronisation (it can be captured in a CUDA
        graph): rows with a negative site are padding, and their keys land in the scratch row."""
        HW = self.shape[0] * self.shape[1]
        keys = _keys(sites, self.shape[1])
        if self.sync_free:
            keys = torch.where(sites[:, 0] >= 0, keys, HW)
        was = self._in_active[keys]
        new = torch.where(removed[:, None], torch.zeros_like(features), features)
        delta = new - self._in_feats[keys]
        self._in_feats[keys] = new
        self._in_active[keys] = ~removed
        moved = delta.ne(0).any(1)
        if self.sync_free:  # mask rows out with (-1, -1) instead of compacting them on the host
            def keep(mask):
                return torch.where(mask[:, None], sites, -1)
            change = Change(keep(moved), delta, keep(~was & ~removed), keep(was & removed))
        else:
            change = Change(sites[moved], delta[moved], sites[~was & ~removed], sites[was & removed])
        self._stamps.zero_()
        block_change = {}
        counts = []
        for layer in self.layers:
            t0 = self._tick(profile)
            change, c = self._layer_step(layer, change)
            counts.append(c)
            layer.stats.ms = self._tock(t0, profile)
            block_change[layer.block] = change
        self.up_changes = []  # what each upsampling layer changed in the output map (read by a head on changed sites)
        for layer in self.up_layers:
            t0 = self._tick(profile)
            change, c = self._layer_step(layer, block_change[layer.block])
            counts.append(c)
            self.up_changes.append(change)
            layer.stats.ms = self._tock(t0, profile)
        sums: dict = {}  # a block's layers share one active map: count it once
        active = torch.stack([sums.setdefault(id(layer.active), layer.active.sum())
                              for layer in self.layers + self.up_layers])
        return active, torch.stack(counts)

    def _replay(self, sites: Tensor, features, removed: Tensor) -> tuple[Tensor, Tensor]:
        """The step as a CUDA graph: the input is padded to a power-of-two capacity (one graph per
        capacity and features function, captured on first use from a step that changes nothing)."""
        n = sites.shape[0]
        cap = graph_capacity(n, 256)
        fn = features if callable(features) else None
        g = self._graphs.get((cap, fn))
        if g is None:
            g = self._capture(cap, fn)
        s_sites, s_feats, s_removed, graph, outputs = g
        s_sites[n:].fill_(-1)
        s_sites[:n].copy_(sites)
        if fn is None:
            s_feats[:n].copy_(features)
        s_removed[n:].fill_(False)
        s_removed[:n].copy_(removed)
        graph.replay()
        return outputs

    @property
    def cuda_graphs(self) -> int:
        """How many CUDA graphs the engine has recorded: one per capacity (and features function) of its updates
        and of its refreshes of every site."""
        return len(self._graphs) + len(self._refresh_graphs)

    def prepare_update(self, capacity: int, features) -> bool:
        """Record now the CUDA graph of an update of up to ``capacity`` changed sites (a power of two, at least
        256) with ``features``, a function of the sites, as :meth:`update` would on the first step of that size;
        it changes no state. Returns whether a graph was recorded (False: not ``cuda_graph``, or recorded)."""
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 256 or capacity & (capacity - 1):
            raise ValueError(f"capacity must be a power of two >= 256, got {capacity!r}")
        if not callable(features):
            raise ValueError(f"features must be a function of the sites, got {type(features).__name__}")
        if not self.cuda_graph or (capacity, features) in self._graphs:
            return False
        self._capture(capacity, features)
        return True

    def _capture(self, cap: int, fn=None):
        s_sites = torch.full((cap, 2), -1, dtype=torch.int32, device=self.device)
        s_feats = None if fn else torch.zeros(cap, self.in_channels, dtype=self.dtype, device=self.device)
        s_removed = torch.zeros(cap, dtype=torch.bool, device=self.device)

        def body():
            return self._step(s_sites, fn(s_sites) if fn else s_feats, s_removed)

        pool = next(iter(self._graphs.values()))[3].pool() if self._graphs else None
        with uncached_autocast():  # the pillar net of fn may run under a caller's autocast
            # the warm-up runs on all-padding input: it changes no state
            graph, outputs = record_graph(body, self.device, pool=pool)
        self._graphs[(cap, fn)] = (s_sites, s_feats, s_removed, graph, outputs)
        return self._graphs[(cap, fn)]

    def _layer_step(self, layer: _Layer, change: Change) -> tuple[Change, Tensor]:
        """One layer of a step; returns the change it passes on and its counts (3,) int64 on the
        device: sites changed, sites changed or with a status change, sites re-evaluated. Without
        ``sync_free``, one host synchronisation (the number of changed sites, which trims the lists
        that size the next layer's work)."""
        ops = torch.ops.lidarops
        base = 4  # stamp values of a step (the maps are zeroed first): base (strided layers' cover),
        # base + 2 (reached), base + 3 (status changed)
        # 1. active status of the output sites (site lists padded with (-1, -1) rows)
        added_count = change.added_count
        if layer.kind == "subm":
            added, removed = change.added, change.removed  # the block's map was updated by its strided layer
        elif layer.kind == "down":  # outputs filled from their first rows, counts in `flips`
            added, removed, flips = ops.sscater_cover_update_(self.block_cover[layer.block], layer.active,
                                                              layer.stamp, base, change.added, change.removed,
                                                              layer.kh, layer.kw, layer.stride, layer.padding)
            added_count = flips[:1]
        else:
            added, removed = ops.sscater_children_(layer.active, change.added, change.removed, layer.kh, layer.kw,
                                                   layer.stride, layer.padding)
        # 2. acc += delta (*) W at the active sites the kernel reaches
        reached = ops.sscater_scatter_(layer.acc, change.sites, change.delta, layer.weight, layer.stride,
                                       layer.padding, layer.transposed, layer.active, change.count,
                                       self.channel_sparse)
        # sites that just became active had no up-to-date acc: compute theirs in full from the input
        # (a transposed layer's child has one parent, whose delta is its whole value: no gather)
        if added.shape[0] and layer.kind != "up":
            w = layer.weight_flat.view(layer.cout, layer.kh, layer.kw, layer.cin)  # contiguous: no copy
            ops.sscater_gather_(layer.acc, layer.input, w, added, layer.stride, layer.padding,
                                added_count if self.sync_free else None)
        # 3. the sites to re-evaluate, each once (an inactive site's acc restarts from zero)
        cand, count = ops.sscater_touch_(layer.stamp, layer.acc, base + 2, reached, added, removed)
        if not self.sync_free:  # trim to the sites listed (free on CPU): finalize's outputs are sized by it
            cand = cand[:int(count)]
        # 4. BN + ReLU there; the sites whose value changed, compacted
        sites, delta, counts = ops.sscater_finalize_compact_(layer.acc, layer.feats, layer.active, cand, count,
                                                             layer.stamp, base + 3, layer.scale, layer.shift)
        if self.sync_free:  # the lists stay padded (at most one row per site of the grid): counts go along
            return Change(sites, delta, added, removed, counts[:1], added_count), counts
        if layer.kind == "down":  # trim the block's status lists, or their padding would grow block by block
            n, na, nr = torch.cat([counts[:1], flips]).tolist()
            added, removed = added[:na], removed[:nr]
        else:
            n = int(counts[0])
        return Change(sites[:n], delta[:n], added, removed), counts

    # ---- helpers ---------------------------------------------------------------------------------

    def _state_max(self) -> Tensor:
        """max |acc| over every accumulator, a 0-d tensor on the device: NaN if one holds a NaN, inf if
        one is infinite (``aminmax`` propagates NaN; one pass over the flat buffer)."""
        if self._accs.numel() == 0:
            return self._accs.new_zeros(())
        lo, hi = torch.aminmax(self._accs)
        return torch.maximum(hi, -lo)

    def _check_input(self, sites: Tensor, features: Tensor, finite: bool = False) -> tuple[Tensor, Tensor]:
        """Sites inside the grid, each once; with ``finite`` (an update, whose deltas stay in the recycled sums)
        finite features. One wait for the device."""
        if not isinstance(sites, Tensor) or sites.dim() != 2 or sites.shape[1] != 2 or sites.is_floating_point():
            raise ValueError(f"sites must be an integer (n, 2) tensor of (y, x), got "
                             f"{getattr(sites, 'dtype', type(sites))} {tuple(getattr(sites, 'shape', ()))}")
        if not isinstance(features, Tensor) or features.shape != (sites.shape[0], self.in_channels):
            raise ValueError(f"features must be ({sites.shape[0]}, {self.in_channels}), got "
                             f"{tuple(getattr(features, 'shape', ()))}")
        if sites.dtype == torch.bool or sites.is_complex():
            raise ValueError(f"sites must be an integer (n, 2) tensor of (y, x), got {sites.dtype}")
        wide = sites.to(device=self.device, dtype=torch.int64)  # checked before the int32 cast: no wrap-around
        features = features.to(device=self.device, dtype=self.dtype)
        if wide.shape[0]:
            H, W = self.shape
            bad = (wide[:, 0] < 0) | (wide[:, 0] >= H) | (wide[:, 1] < 0) | (wide[:, 1] >= W)
            key = wide[:, 0] * W + wide[:, 1]
            sorted_keys = torch.sort(torch.where(bad, -1 - torch.arange(len(key), device=key.device), key)).values
            repeated = (sorted_keys[1:] == sorted_keys[:-1]) & (sorted_keys[1:] >= 0)
            nonfinite = ~torch.isfinite(features).all(1) if finite else torch.zeros_like(bad)
            flags = torch.stack([bad.any(), repeated.any(), nonfinite.any()]).tolist()  # one wait for the device
            if flags[0]:
                raise ValueError(f"sites lie outside the ({H}, {W}) grid, e.g. {wide[bad][0].tolist()}")
            if flags[1]:
                dup = sorted_keys[1:][repeated][0].item()
                raise ValueError(f"sites must each appear once: ({dup // W}, {dup % W}) is given more than once "
                                 "(a site's delta would be applied twice)")
            if flags[2]:
                row = int(torch.nonzero(nonfinite)[0])
                raise ValueError(f"features must be finite (a NaN or inf would stay in the recycled state): row {row} "
                                 f"at site {wide[row].tolist()} is {features[row].tolist()[:8]}")
        return wide.to(torch.int32), features

    def _tick(self, profile: bool) -> float:
        if profile and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def _tock(self, t0: float, profile: bool) -> float:
        if profile and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return (time.perf_counter() - t0) * 1e3


def _dense_format(device: torch.device) -> torch.memory_format:
    """The memory format of a dense refresh's convolutions (:data:`DENSE_CHANNELS_LAST`): channels-last takes the
    maps' own memory without a transpose."""
    return torch.channels_last if DENSE_CHANNELS_LAST.get(device.type, False) else torch.contiguous_format


def _dense_conv(layer: _Layer, x_nchw: Optional[Tensor] = None) -> Tensor:
    """The layer's convolution (no bias) of its whole input map (or of ``x_nchw (Tensor[Cin, H, W])``, the same
    values in NCHW), (Cout, Ho, Wo) in the device's format, by torch's dense convolution."""
    F = torch.nn.functional
    # (1, Cin, H, W), a view of the channels-last map or a copy in the device's format
    x = x_nchw[None] if x_nchw is not None else \
        layer.input.permute(2, 0, 1).unsqueeze(0).contiguous(memory_format=_dense_format(layer.input.device))
    cudnn = torch.backends.cudnn
    # float32 sums, as the recycled layers' (TF32 would round the inputs to 10 bits); the user's other flags kept
    with cudnn.flags(enabled=cudnn.enabled, benchmark=cudnn.benchmark, deterministic=cudnn.deterministic,
                     allow_tf32=False):
        if layer.transposed:
            y = F.conv_transpose2d(x, layer.weight_dense, None, layer.stride, layer.padding)
        else:
            y = F.conv2d(x, layer.weight_dense, None, layer.stride, layer.padding)
    return y[0]


def _batch0(sites: Tensor) -> Tensor:
    return torch.cat([sites.new_zeros(sites.shape[0], 1), sites], 1).int()
