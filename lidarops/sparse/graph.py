"""A sparse network replayed as one CUDA graph while its sites stay the same.

An eager sparse forward is bound by the host (Python and a few launches per layer, with the GPU idle a
quarter of the time); the same forward on cached kernel maps has no host synchronisation, so it can be
recorded once as a CUDA graph and replayed for new features at the same sites: a stationary sensor's fixed
grid, a region of interest, the same frame through several heads, the sites of a stream between changes.
:class:`GraphedSparseNet` does the bookkeeping:

    graphed = GraphedSparseNet(net)      # net: a sparse network in eval mode on a CUDA device
    with torch.no_grad():
        y = graphed(x)                   # first sites: eager, records the kernel maps the layers build
        y = graphed(x2)                  # the same sites again (the same indices, or equal ones): recorded
        y = graphed(x3)                  # ... and replayed from then on
        y = graphed(other)               # other sites: eager again, and recorded when they come back

Each call's result equals ``net(x)`` (the same kernels on the same maps). It runs eagerly, and records
nothing, on CPU, in training mode and where autograd needs the result.
"""
from __future__ import annotations

import contextlib
from typing import Any, Optional

import torch
from torch import Tensor, nn

from lidarops._cuda_graphs import record_graph, uncached_autocast
from lidarops.ops.validation import validation
from lidarops.sparse import functional as Fs
from lidarops.sparse.tensor import SparseConvTensor

__all__ = ["GraphedSparseNet"]


def _versions(tensors: list) -> list:
    """Which tensor sits in each slot, where it lives and its in-place version: a change means a graph reads stale
    values (a BatchNorm's folded affine is computed when recorded) or freed memory."""
    present = [t for t in tensors if t is not None]  # (an empty slot, a bias=False, is None: its id says so)
    try:
        return [id(t) for t in tensors] + [t.data_ptr() for t in present] + [t._version for t in present]
    except RuntimeError:  # an inference tensor: no version counter
        return [id(t) for t in tensors] + [(t.data_ptr(), None if t.is_inference() else t._version) for t in present]


def _map_outputs(out, fn):
    if isinstance(out, SparseConvTensor):
        return SparseConvTensor._derived(fn(out.features), out.indices, out.spatial_shape, out.batch_size,
                                         out.indice_dict)
    if isinstance(out, Tensor):
        return fn(out)
    if isinstance(out, (list, tuple)):
        mapped = [_map_outputs(o, fn) for o in out]
        return type(out)(*mapped) if hasattr(out, "_fields") else type(out)(mapped)
    if isinstance(out, dict):
        return type(out)((k, _map_outputs(v, fn)) for k, v in out.items())
    return out


class GraphedSparseNet:
    """``net`` on :class:`SparseConvTensor` inputs, replayed as one CUDA graph for sites it has seen twice.

    Args:
        net (nn.Module): a sparse network taking one ``SparseConvTensor`` (``SparseSequential``, a backbone, any
            module made of ``lidarops.sparse`` or ``lidarops.compat.spconv`` layers).
        clone_outputs (bool): return copies of the graph's outputs (default). ``False`` returns the graph's own
            output tensors, which the next replay overwrites: faster, for callers that use a result before the
            next call.

    A call on sites not seen before runs ``net`` eagerly, as it would without this class, and remembers the
    kernel maps its layers register under an ``indice_key``. When the next call has the same sites (the same
    indices tensor, unchanged in place, or an equal one: one comparison on the device, one host
    synchronisation), the forward is recorded on those maps (a warm-up and the capture, on a side stream) and
    replayed; later calls on those sites copy their features into the graph's input and replay. One graph is kept:
    a call on other sites runs eagerly and becomes the next candidate. A call on the recorded sites records the
    graph again (on the same maps) when the network's parameters or buffers have changed (replaced or changed in
    place, in the modules the network had when wrapped: wrap it again after adding modules), or the autocast state,
    the TF32 flags, the features' dtype or channels differ.

    The graph is recorded with lidarops' value checks off (``lidarops.validation(False)``): the eager call that
    found the sites checked them, and a check is a host read, which a graph cannot hold.

    Runs eagerly and records nothing: on CPU; while ``net`` is in training mode; when autograd needs the result
    (gradients enabled and the features or a parameter requiring them); under ``torch.compile``. A forward that
    cannot be recorded runs eagerly from then on, and :attr:`reason` says why: a strided, transposed or pooling
    layer without an ``indice_key`` (its map is built every call, with a host read), an ``indice_key`` registered on
    two different sites by two branches, or a host read of the network's own (the capture then fails).

    Attributes:
        replays, captures, eager_calls (int): how the calls ran.
        reason (str or None): why this network is no longer recorded, if it is not.
    """

    def __init__(self, net: nn.Module, clone_outputs: bool = True):
        if not isinstance(net, nn.Module):
            raise ValueError(f"net must be a torch.nn.Module, got {type(net).__name__}")
        if not isinstance(clone_outputs, bool):
            raise ValueError(f"clone_outputs must be True or False, got {clone_outputs!r}")
        self.net = net
        self.clone_outputs = clone_outputs
        self.replays = self.captures = self.eager_calls = 0
        self.reason: Optional[str] = None
        # the parameter and buffer slots of every module, read at each call: a tensor replaced in a slot is seen
        self._slots = [(d, name) for m in net.modules() for d in (m._parameters, m._buffers) for name in d]
        self._candidate = None  # (sites, maps, key) of the last eager call on sites without a graph
        self._graph = None      # (sites, key, graph, static features, outputs, static input with its maps)

    # ---- what a call is compared by ----------------------------------------------------------------------

    def _key(self, x: SparseConvTensor) -> tuple:
        f = x.features
        dev = f.device.type
        amp = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else None
        return (f.dtype, f.shape[1], f.device, amp, torch.backends.cuda.matmul.allow_tf32,
                torch.backends.cudnn.allow_tf32, _versions(self._tensors()))

    def _tensors(self) -> list:
        return [d.get(name) for d, name in self._slots]

    @staticmethod
    def _sites(x: SparseConvTensor) -> tuple:
        i = x.indices
        return (i, None if i.is_inference() else i._version, tuple(x.spatial_shape), x.batch_size)

    @staticmethod
    def _same_sites(x: SparseConvTensor, sites: tuple) -> bool:
        indices, version, shape, batch = sites
        i = x.indices
        if tuple(x.spatial_shape) != shape or x.batch_size != batch or i.shape != indices.shape:
            return False
        if i is indices and version is not None and i._version == version:
            return True
        if version is not None and indices._version != version:  # the recorded tensor changed in place
            return False
        return i.device == indices.device and bool(torch.equal(i, indices))

    def _eager_only(self, x: SparseConvTensor) -> bool:
        if x.features.device.type != "cuda" or self.net.training or torch.compiler.is_compiling():
            return True
        return torch.is_grad_enabled() and (x.features.requires_grad
                                            or any(t is not None and t.requires_grad for t in self._tensors()))

    # ---- calls ----------------------------------------------------------------------------------------

    def __call__(self, x: SparseConvTensor) -> Any:
        if not isinstance(x, SparseConvTensor):
            raise ValueError(f"x must be a SparseConvTensor, got {type(x).__name__}")
        if self.reason is not None or self._eager_only(x):
            self.eager_calls += 1
            return self.net(x)
        key = self._key(x)
        g = self._graph
        if g is not None and self._same_sites(x, g[0]):
            if g[1] != key:  # the same sites and maps, other weights, precision or dtype: recorded again
                self._graph = None
                self._graph = g = self._record(g[0], g[5].indice_dict, key, x.features)
                if g is None:
                    return self._eager(x, key)
            return self._replay(g, x.features)
        c = self._candidate
        if c is not None and c[2] == key and self._same_sites(x, c[0]):
            self._candidate = None
            self._graph = None  # its memory goes back before the new graph takes its own
            self._graph = self._record(c[0], c[1], key, x.features)
            if self._graph is not None:
                return self._replay(self._graph, x.features)
        return self._eager(x, key)

    def _eager(self, x: SparseConvTensor, key: tuple) -> Any:
        self.eager_calls += 1
        maps: dict = {}
        with Fs.recording_maps(maps):
            out = self.net(x)
        conflict, unkeyed = maps.pop(Fs.CONFLICT, None), maps.pop(Fs.UNKEYED, None)
        if conflict is not None:
            self._eager_from_now(f"two layers registered indice_key {conflict!r} on different sites (branches), so no "
                                 "one indice_dict holds the network's maps")
        elif unkeyed is not None:
            self._eager_from_now(f"a {unkeyed} layer without an indice_key builds its kernel map every call, with a host "
                                 "read (its output count): give strided, transposed and pooling layers an indice_key")
        elif self.reason is None:  # (a failed recording has just ruled graphs out)
            self._candidate = (self._sites(x), maps, key)
        return out

    def _eager_from_now(self, reason: str) -> None:
        self.reason = reason
        self._candidate = self._graph = None

    def _replay(self, g: tuple, features: Tensor) -> Any:
        _, _, graph, static, outputs, _ = g
        static.copy_(features)
        graph.replay()
        self.replays += 1
        return _map_outputs(outputs, torch.clone) if self.clone_outputs else outputs

    def _record(self, sites: tuple, maps: dict, key: tuple, features: Tensor):
        indices, _, shape, batch = sites
        with torch.inference_mode(False):  # a static input a later call outside inference mode can copy into
            static = torch.empty_like(features)
        static.copy_(features)
        x = SparseConvTensor._derived(static, indices, shape, batch, maps)

        def run():  # the sites were checked by the eager call that found them (a check is a host read, which a
            # capture cannot hold: sites made under inference mode keep no version counter, so dense() would re-check)
            with torch.inference_mode(False), torch.no_grad(), uncached_autocast(), validation(False):
                return self.net(x)

        # every map's row order (and its inverse's), which a capture cannot make: in a replay the order costs no
        # host time and saves kernel time, however few layers run on the map
        for km in maps.values():
            km.order
            if km._inverse is not None:
                km._inverse.order
        try:
            graph, outputs = record_graph(run, static.device, capture_error_mode="thread_local")
        except (RuntimeError, ValueError) as e:  # a host read in the forward (the network's own): not recordable
            self._eager_from_now("the forward cannot be recorded as a CUDA graph (it reads from the device, which a "
                                 "capture forbids): " + str(e).splitlines()[0])
            with contextlib.suppress(RuntimeError):
                torch.cuda.synchronize(static.device)
            return None
        self.captures += 1
        # the maps (and the input holding them) stay alive with the graph: it reads their memory at every replay
        return (sites, key, graph, static, outputs, x)

    def reset(self) -> None:
        """Drop the recorded graph and the candidate sites (and the reason, if recording had failed): the next
        call runs eagerly."""
        self._graph = self._candidate = None
        self.reason = None

    def __repr__(self) -> str:
        state = "eager only: " + self.reason if self.reason else ("graph recorded" if self._graph else "no graph yet")
        return (f"GraphedSparseNet({type(self.net).__name__}, {state}; replays={self.replays}, "
                f"captures={self.captures}, eager_calls={self.eager_calls})")
