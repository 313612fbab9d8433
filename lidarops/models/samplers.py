"""Point cloud samplers behind one interface, the baselines of CAS-Net (issue 37) and CAS-Net itself.

Every sampler is a callable ``sampler(points, m, lengths=None) -> indices``:

* ``points (Tensor[B, N, C])``: floating point, ``C >= 3``, the first three channels are ``x, y, z``
  (intensity and other channels ride along and are ignored by the geometric samplers).
* ``m (int)``: samples per cloud, >= 1.
* ``lengths (Tensor[B], optional)``: valid points per cloud (a ragged batch: the valid points of cloud
  ``b`` are ``points[b, :lengths[b]]``); default ``N``.
* returns ``Tensor[B, m]`` int64: indices into ``N``, ``m`` distinct valid points when the cloud has at
  least ``m`` of them; otherwise all of its points, then ``-1`` padding (the core ops' convention, as
  :func:`lidarops.fps`). :func:`sample_features` turns the indices into rows (``-1`` gives a zero row).

The samplers:

* :class:`RandomSampler`: uniform without replacement, seeded.
* :class:`FPSSampler`: exact farthest point sampling, :func:`lidarops.fps` (start at the first valid
  point, ties to the lower index).
* :class:`ChunkedFPSSampler`: FPS run per spatially coherent chunk (:func:`spatial_segments`) as the
  CAS-Net paper runs its FPS baseline on clouds cut into segments of at most 8,192 points.
* :class:`lidarops.models.casnet.CASNetSampler`: the learned sampler (in ``casnet.py``).

Arguments are checked first: ``ValueError`` naming ``points``, ``m`` or ``lengths`` and what was received.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from lidarops._checks import integer
from lidarops.ops.neighbors import fps, gather
from lidarops.ops.validation import (check_output_size, check_positive_int, check_same_device, check_tensor,
                                     check_values, describe, lengths_or_full, validation, value_checks_enabled)

__all__ = ["Sampler", "RandomSampler", "FPSSampler", "ChunkedFPSSampler", "sample_features", "spatial_segments",
           "segment_shares", "check_sampler_args"]


def check_sampler_args(points, m, lengths=None, coords: bool = False) -> tuple[int, Tensor]:
    """The shared argument checks of the samplers.

    Args:
        points: must be a floating ``(B, N, C)`` tensor with ``C >= 3``.
        m: must be a positive int whose ``(B, m)`` output fits (refused before allocating).
        lengths: ``None`` or an integer ``(B,)`` tensor on ``points``' device with values in ``[0, N]``.
        coords (bool): also check (with the value checks on) that the coordinates are finite and within
            :func:`lidarops.ops.validation.coordinate_bound` (samplers that compare coordinates).

    Returns:
        ``(m, lengths)``: ``m`` as an int, ``lengths`` as an int64 ``(B,)`` tensor (``N`` where not given).

    Raises:
        ValueError: naming ``points``, ``m`` or ``lengths``.
    """
    check_tensor(points, "points")
    if points.dim() != 3 or points.shape[-1] < 3:
        raise ValueError(f"points must be (B, N, C) with C >= 3 (x, y, z first), got {describe(points)}")
    if not points.is_floating_point():
        raise ValueError(f"points must be floating point, got {describe(points)}")
    m = check_positive_int(m, "m")
    check_output_size((points.shape[0], m), f"m={m}", "the sample indices")
    given = lengths
    lengths = lengths_or_full(lengths, points, "lengths")
    if value_checks_enabled() and points.device.type != "meta":
        n = points.shape[1]
        ranged = []
        if given is not None and lengths.numel():
            ranged = [(lengths, 0, n, lambda: f"lengths must lie in [0, {n}], got {lengths.tolist()}")]
        check_values(coords=[(points[..., :3], "points")] if coords else [], ranged=ranged)
    return m, lengths


class Sampler:
    """The sampler interface: ``sampler(points, m, lengths=None) -> Tensor[B, m] int64`` (see the module
    docstring for the contract). Subclasses implement :meth:`sample` on checked arguments."""

    #: whether the sampler reads coordinates (then NaN/inf/huge coordinates are refused up front)
    reads_coordinates = True

    def __call__(self, points: Tensor, m: int, lengths: Tensor | None = None) -> Tensor:
        m, full = check_sampler_args(points, m, lengths, coords=self.reads_coordinates)
        return self.sample(points, m, full)

    def sample(self, points: Tensor, m: int, lengths: Tensor) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class RandomSampler(Sampler):
    """Uniform random sampling without replacement: per cloud the first ``m`` entries of a random
    permutation of its valid points.

    The permutations are drawn on the CPU from one ``torch.Generator`` seeded with ``seed`` at
    construction (so CPU and CUDA tensors get the same indices): a fresh sampler with the same seed
    repeats the same sequence of calls exactly; successive calls of one sampler draw new samples (an
    epoch of training sees new subsets). :meth:`reset` starts the sequence again.

    Args:
        seed (int): the generator's seed, an int in [0, 2^63).
    """

    reads_coordinates = False

    def __init__(self, seed: int = 0):
        self.seed = integer(seed, "seed", 0, 2**63 - 1)
        self.reset()

    def reset(self) -> None:
        """Re-seed: the next calls repeat those of a fresh sampler."""
        self.generator = torch.Generator().manual_seed(self.seed)

    def sample(self, points: Tensor, m: int, lengths: Tensor) -> Tensor:
        B = points.shape[0]
        out = torch.full((B, m), -1, dtype=torch.int64)
        for b, n in enumerate(lengths.tolist()):
            if n:
                perm = torch.randperm(n, generator=self.generator)[:m]
                out[b, :perm.numel()] = perm
        return out.to(points.device)

    def __repr__(self) -> str:
        return f"RandomSampler(seed={self.seed})"


class FPSSampler(Sampler):
    """Exact farthest point sampling of the ``x, y, z`` channels: :func:`lidarops.fps` (selection order,
    the first valid point first, ties to the lower index, a point never twice, ``-1`` past the cloud).

    Args:
        method (str): passed to :func:`lidarops.fps` (``"auto"``, ``"plain"``, ``"leaves"``); every method
            returns the same indices.
    """

    def __init__(self, method: str = "auto"):
        if method not in ("auto", "plain", "leaves"):
            raise ValueError(f"method must be one of ['auto', 'leaves', 'plain'], got {method!r}")
        self.method = method

    def sample(self, points: Tensor, m: int, lengths: Tensor) -> Tensor:
        return fps(points[..., :3], m, lengths=lengths, method=self.method)

    def __repr__(self) -> str:
        return f"FPSSampler(method={self.method!r})"


class ChunkedFPSSampler(Sampler):
    """FPS per spatially coherent chunk, as the CAS-Net paper runs its FPS baseline on clouds cut into
    segments of at most 8,192 points (much cheaper than FPS of the whole cloud, and what the paper's
    tables compare against).

    Per cloud: :func:`spatial_segments` cuts the ``n`` valid points into ``ceil(n / chunk)`` chunks of at
    most ``chunk`` points (balanced k-d splits along the longest axis); chunk ``i`` of ``s_i`` points gets
    the share ``m_i`` of :func:`segment_shares` (proportional to ``s_i``, summing to ``min(m, n)``);
    :func:`lidarops.fps` picks ``m_i`` points of the chunk (its points in their original index order, so it
    starts at the chunk's lowest index and breaks ties to the lower original index). The result is the
    chunks' picks concatenated in chunk order, each in FPS order, then ``-1`` padding. With
    ``chunk >= n`` it is exactly :class:`FPSSampler`. All chunks of the batch go through one
    :func:`lidarops.fps` call.

    Args:
        chunk (int): most points per chunk (default 8,192, the paper's segment size).
    """

    def __init__(self, chunk: int = 8192):
        self.chunk = check_positive_int(chunk, "chunk")

    def sample(self, points: Tensor, m: int, lengths: Tensor) -> Tensor:
        B = points.shape[0]
        xyz = points[..., :3]
        device = points.device
        out = torch.full((B, m), -1, dtype=torch.int64, device=device)
        pieces, shares, owners = [], [], []  # (chunk indices, share, (b, offset in the output))
        for b, n in enumerate(lengths.tolist()):
            if n == 0:
                continue
            segs = spatial_segments(xyz[b, :n], self.chunk)
            sh = segment_shares([s.numel() for s in segs], min(m, n))
            offset = 0
            for s, k in zip(segs, sh):
                if k:
                    pieces.append(s)
                    shares.append(k)
                    owners.append((b, offset))
                offset += k
        if not pieces:
            return out
        # one fps call for every chunk of the batch: chunks padded to the longest, with their lengths
        size = max(p.numel() for p in pieces)
        batch = xyz.new_zeros(len(pieces), size, 3)
        for i, ((b, _), p) in enumerate(zip(owners, pieces)):
            batch[i, :p.numel()] = xyz[b, p]
        chunk_lengths = torch.tensor([p.numel() for p in pieces], dtype=torch.int64, device=device)
        picked = fps(batch, max(shares), lengths=chunk_lengths)
        for i, ((b, offset), p, k) in enumerate(zip(owners, pieces, shares)):
            out[b, offset:offset + k] = p[picked[i, :k]]  # FPS order: the first k of more are FPS of k
        return out

    def __repr__(self) -> str:
        return f"ChunkedFPSSampler(chunk={self.chunk})"


def sample_features(features: Tensor, indices: Tensor) -> Tensor:
    """The rows of ``features`` a sampler picked (:func:`lidarops.gather`).

    Args:
        features (Tensor[B, N, C]): any per-point values (``x, y, z``, intensity, learned features).
        indices (Tensor[B, m] integer): in ``[-1, N)``, as a sampler returns them.

    Returns:
        Tensor[B, m, C]: ``out[b, i] = features[b, indices[b, i]]``; a zero row where the index is ``-1``.
        Differentiable with respect to ``features``.

    Raises:
        ValueError: naming ``features`` or ``indices`` (shape, dtype, device, indices out of range).
    """
    check_tensor(features, "features")
    check_tensor(indices, "indices")
    if features.dim() != 3:
        raise ValueError(f"features must be (B, N, C), got {describe(features)}")
    if indices.dim() != 2 or indices.shape[0] != features.shape[0]:
        raise ValueError(f"indices must be (B, m) with B = {features.shape[0]}, got {describe(indices)}")
    if indices.is_floating_point() or indices.is_complex() or indices.dtype == torch.bool:
        raise ValueError(f"indices must be an integer tensor, got {describe(indices)}")
    check_same_device([("features", features), ("indices", indices)])
    n = features.shape[1]
    if value_checks_enabled() and indices.numel() and indices.device.type != "meta":
        check_values(ranged=[(indices.to(torch.int64), -1, n - 1,
                              lambda: f"indices must lie in [-1, {n}), got values in "
                                      f"[{int(indices.min())}, {int(indices.max())}]")])
    with validation(False):  # checked above, under this function's argument names
        return gather(features, indices)


def spatial_segments(xyz: Tensor, max_points: int) -> list[Tensor]:
    """Cut one cloud into ``ceil(n / max_points)`` spatially coherent segments of balanced size.

    A k-d split: a segment of ``n`` points that must become ``c`` pieces is split along its longest
    axis (largest extent of ``x``, ``y``, ``z``; ties to the first axis) at the ``floor(c/2) / c``
    quantile of that coordinate (a stable sort: equal coordinates keep their index order), the two
    halves becoming ``floor(c/2)`` and ``c - floor(c/2)`` pieces. Every segment then holds at most
    ``max_points`` points and the sizes differ by at most a few points; segments are compact boxes
    rather than long slabs, so local neighbourhoods (ball query, attention) are rarely cut.

    Args:
        xyz (Tensor[n, 3+]): one cloud's points (only the first three channels are read).
        max_points (int): most points per segment.

    Returns:
        list of int64 Tensors: the indices of each segment into ``xyz``, each sorted ascending, in the
        split's left-to-right order; together a partition of ``range(n)``. Empty for ``n = 0``.
    """
    max_points = check_positive_int(max_points, "max_points")
    check_tensor(xyz, "xyz")
    if xyz.dim() != 2 or xyz.shape[-1] < 3:
        raise ValueError(f"xyz must be (n, C) with C >= 3, got {describe(xyz)}")
    n = xyz.shape[0]
    if n == 0:
        return []
    pts = xyz[:, :3]
    out: list[Tensor] = []

    def split(idx: Tensor, c: int) -> None:
        if c == 1:
            out.append(torch.sort(idx).values)
            return
        p = pts[idx]
        axis = int(torch.argmax(p.amax(0) - p.amin(0)))
        order = torch.sort(p[:, axis], stable=True).indices
        c_left = c // 2
        n_left = idx.numel() * c_left // c  # floor: both halves then fit their pieces (see the docstring)
        split(idx[order[:n_left]], c_left)
        split(idx[order[n_left:]], c - c_left)

    split(torch.arange(n, device=xyz.device), math.ceil(n / max_points))
    return out


def segment_shares(sizes: list[int], k: int, caps: list[int] | None = None) -> list[int]:
    """How many of ``k`` samples each segment gives: proportional to its size, never more than its size
    (or ``caps``), summing to ``min(k, sum of what the segments can give)``.

    The proportional shares are the differences of ``floor(k * S_i / n)`` over the cumulative sizes
    ``S_i`` (exact when no cap binds: each share within one of ``k * s_i / n``); what a cap cuts is
    handed, one sample at a time, to the segments with room, largest size first (ties to the first).

    Args:
        sizes: points per segment.
        k (int): samples wanted.
        caps: most samples per segment (default: its size).

    Returns:
        list of int: the shares, in the order of ``sizes``.
    """
    caps = [min(s, c) for s, c in zip(sizes, caps)] if caps is not None else list(sizes)
    n = sum(sizes)
    k = min(k, sum(caps))
    if n == 0 or k <= 0:
        return [0] * len(sizes)
    shares, cum = [], 0
    for s in sizes:
        shares.append((k * (cum + s)) // n - (k * cum) // n)
        cum += s
    shares = [min(sh, c) for sh, c in zip(shares, caps)]
    left = k - sum(shares)
    by_size = sorted(range(len(sizes)), key=lambda i: (-sizes[i], i))
    while left > 0:
        for i in by_size:
            if left and shares[i] < caps[i]:
                shares[i] += 1
                left -= 1
    return shares
