"""CAS-Net: learned attention-based point cloud simplification (Rozsa et al. 2026, building on Chen et al.,
ICME 2023). Read it top to bottom:

- ``embedding``: :class:`FeatureEmbedding`: per point its ``k`` neighbours (:func:`lidarops.ball_query`,
  detection: ``k = 32``, ``r = 2 m``; or :func:`lidarops.knn`), edge features ``[p, p_j - p]`` (6
  channels), a shared MLP 6 -> 64 -> 64 (1x1 conv + BN + LeakyReLU 0.2), the max over the neighbours ->
  ``(B, 64, N)``. The ops' padding slots (index -1) are never points: they enter neither the MLP's
  BatchNorm statistics nor the max.
- ``attention``: ``num_oa_layers`` offset-attention layers (PCT; :mod:`lidarops.models.offset_attention`),
  applied in sequence, their outputs concatenated -> ``(B, 64 * num_oa_layers, N)`` (192 for the paper's 3).
- ``head``: :class:`SamplingHead`: per point ``concat(F, xyz)`` -> 1x1 conv + BN -> 1x1 conv to ``m``
  channels + BN -> logits ``(B, m, N)`` / temperature -> softmax over ``N``: the soft matrix ``S~``.
- :func:`matrix_sample`: the hard matrix ``S`` (one-hot argmax of each row) with the straight-through
  gradient ``S - stopgrad(S~) + S~`` (``mode="hard"``, the paper's AHSN, a true subset of the input) or
  ``S~`` itself (``mode="soft"``, ASSN); either samples any per-point features (x, y, z, intensity, ...).
- Losses: :func:`casnet_loss` = task loss + alpha * Chamfer(sampled xyz, input xyz) + beta * the cosine
  loss of the rows of ``S~`` (:mod:`lidarops.models.casnet_losses`).
- ``head="anchored"`` (ours): :class:`AnchoredHead` instead of the sampling matrix's head: each row anchored at a
  farthest point sample, choosing among its nearest points; an untrained head is FPS, and ``m`` is free per call.
  :meth:`CASNet.pick` gives its picks without the ``(B, m, N)`` matrices.
- Large clouds: :func:`segment_and_sample` (segments of at most 8,192 points, as the paper);
  :class:`CASNetSampler` puts the model behind the samplers' interface (:mod:`lidarops.models.samplers`).

Duplicates. The rows of ``S`` are independent argmaxes, so two rows may pick the same point: the hard
output is then a subset with repeats (fewer distinct points than ``m``). AHSN does not prevent it: the
reference code (github.com/yuanhui0325/CAS-Net, ``SLRS.forward``) takes each row's plain argmax and
reports how many distinct points came out; only the cosine loss pushes the rows' distributions apart, a
soft deterrent. Measured here (CPU, LiDAR-like clouds): an untrained model keeps 194 distinct points of
m = 1,024 from an 8,192-point segment, and about 60-68 of m = 128 from 1,024 points (eval mode; about 91
in training mode); 40 Adam steps on Chamfer + cosine alone left about 70 of 128.
:attr:`CASNetOutput.num_duplicates` counts them; ``dedup=True`` (ours, off by default as in the paper)
reassigns the rows greedily (:func:`greedy_distinct_rows`) so that every cloud with at least ``m`` valid
points yields ``m`` distinct ones; the straight-through gradient is unchanged (it flows through ``S~``).

Shapes follow the rest of lidarops: points ``(B, N, C)`` with ``x, y, z`` first, ragged batches through
``lengths (B,)`` (the valid points of cloud ``b`` are ``points[b, :lengths[b]]``), indices int64.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops._checks import flag, positive_int, real
from lidarops.models import folded
from lidarops.models.casnet_losses import chamfer_distance, selection_cosine_loss
from lidarops.models.offset_attention import OffsetAttention
from lidarops.models.samplers import Sampler, segment_shares, spatial_segments
from lidarops.ops.assign import greedy_assign
from lidarops.ops.neighbors import ball_query, fps, gather, knn
from lidarops.ops.validation import (check_positive_int, check_tensor, check_values, describe, lengths_or_full,
                                     validation, value_checks_enabled)

__all__ = ["CASNet", "CASNetOutput", "FeatureEmbedding", "SamplingHead", "AnchoredHead", "matrix_sample",
           "greedy_distinct_rows", "count_duplicates", "segment_and_sample", "CASNetSampler", "casnet_loss",
           "load_casnet"]

_MODES = ("hard", "soft")
_NEIGHBORS = ("ball", "knn")
_HEADS = ("matrix", "anchored")


@dataclass
class CASNetOutput:
    """What :meth:`CASNet.forward` returns.

    Attributes:
        sampled (Tensor[B, m, C]): the sampled points with all their channels, in ``points``' dtype. Hard
            mode: exactly the input rows ``points[b, indices[b]]`` (the straight-through term adds an
            exact zero); soft mode: ``S~ @ points`` (convex combinations, not input points).
        indices (Tensor[B, m] int64 | None): the rows' picks (hard mode); ``None`` in soft mode.
        soft_matrix (Tensor[B, m, N]): ``S~``, each row a distribution over the valid points (zeros at
            padded points); what the cosine loss reads.
        logits (Tensor[B, m, N]): the head's output divided by the temperature; ``-inf`` at padded points.
        lengths (Tensor[B] int64): valid input points per cloud (the Chamfer loss reads it).
        num_duplicates (Tensor[B] int64 | None): hard mode: ``m`` minus the distinct points picked.
        mode (str): ``"hard"`` or ``"soft"``.
    """

    sampled: Tensor
    indices: Optional[Tensor]
    soft_matrix: Tensor
    logits: Tensor
    lengths: Tensor
    num_duplicates: Optional[Tensor]
    mode: str

    @property
    def sampled_xyz(self) -> Tensor:
        """Tensor[B, m, 3]: the sampled points' ``x, y, z``."""
        return self.sampled[..., :3]


class FeatureEmbedding(nn.Module):
    """Edge features of each point's neighbourhood through a shared MLP, max-pooled: ``(B, 64, N)``.

    Args:
        k (int): neighbours per point.
        radius (float): ball radius (``neighbors="ball"``), > 0.
        neighbors (str): ``"ball"`` (:func:`lidarops.ball_query`: the first ``k`` points, in index order,
            strictly within ``radius``; a point is always within its own ball, so every valid point has at
            least one neighbour) or ``"knn"`` (:func:`lidarops.knn`: the ``k`` nearest, itself included).
        channels (int): the MLP's width (64 in the paper).

    Padding: the ops pad missing neighbours with index -1. Those slots are dropped before the MLP (its
    BatchNorm statistics see only real edges) and from the max; a point with no neighbour at all (a
    padded point of a ragged batch, or a radius whose square underflows) gets the zero vector. (The
    reference code's PointNet++ ball query repeats the first neighbour instead: the same max, but its
    BatchNorm statistics count the repeats.)
    """

    def __init__(self, k: int = 32, radius: float = 2.0, neighbors: str = "ball", channels: int = 64):
        super().__init__()
        self.k = positive_int(k, "k")
        self.radius = real(radius, "radius", 0.0, lo_open=True)
        if neighbors not in _NEIGHBORS:
            raise ValueError(f"neighbors must be one of {list(_NEIGHBORS)}, got {neighbors!r}")
        self.neighbors = neighbors
        self.channels = positive_int(channels, "channels")
        self.mlp = nn.Sequential(
            nn.Conv1d(6, channels, 1, bias=False), nn.BatchNorm1d(channels), nn.LeakyReLU(0.2),
            nn.Conv1d(channels, channels, 1, bias=False), nn.BatchNorm1d(channels), nn.LeakyReLU(0.2),
        )

    def neighbour_indices(self, xyz: Tensor, lengths: Tensor) -> Tensor:
        """Tensor[B, N, k] int64: each point's neighbours, -1 padding (and all -1 for padded points)."""
        with validation(False):  # the caller checked the points and lengths
            if self.neighbors == "ball":
                _, idx = ball_query(xyz, xyz, self.radius, self.k, lengths, lengths)
            else:
                _, idx = knn(xyz, xyz, self.k, lengths, lengths)
        return idx

    def forward(self, xyz: Tensor, lengths: Tensor) -> Tensor:
        """Args: xyz (Tensor[B, N, 3]) in the parameters' dtype; lengths (Tensor[B] int64).
        Returns: Tensor[B, channels, N]."""
        if self.neighbors == "knn" and self.k == 1:
            # a point's nearest is itself or a point at its place: the edge is [p, 0] either way, no search needed
            B, N, _ = xyz.shape
            idx = torch.arange(N, device=xyz.device).view(1, N, 1).expand(B, N, 1)
            valid = idx < lengths.view(B, 1, 1)
            if self.training:  # BatchNorm statistics of the real points only
                return self.embed(xyz, idx, valid)
            h = self.mlp(torch.cat([xyz, torch.zeros_like(xyz)], -1).transpose(1, 2))  # (B, C, N)
            return torch.where(valid.view(B, 1, N), h, torch.zeros((), dtype=h.dtype, device=h.device))
        idx = self.neighbour_indices(xyz.detach(), lengths)
        return self.embed(xyz, idx, idx >= 0)

    def rows(self, xyz: Tensor, lengths: Tensor) -> Tensor:
        """:meth:`forward` in eval mode for clouds that fill ``N``, as rows ``(B, N, channels)``; the fast
        variant's (``knn``, ``k = 1``: the edge ``[p, 0]``) as two folded layers."""
        if self.training or self.neighbors != "knn" or self.k != 1:
            return self(xyz, lengths).transpose(1, 2)
        def build():
            w1, b1 = folded.conv_bn(self.mlp[0], self.mlp[1])
            return (w1[:, :3], b1, *folded.conv_bn(self.mlp[3], self.mlp[4]))  # p_j - p = 0: only p's 3 inputs

        w1, b1, w2, b2 = folded.cached(self, "rows", folded.compute_dtype(xyz), build)
        h = F.leaky_relu(F.linear(xyz, w1, b1), 0.2, inplace=True)
        return F.leaky_relu(F.linear(h, w2, b2), 0.2, inplace=True)

    def embed(self, xyz: Tensor, idx: Tensor, valid: Tensor) -> Tensor:
        """The embedding of given neighbourhoods: ``max over valid j of MLP([p, p_j - p])``.

        Args:
            xyz (Tensor[B, N, 3]); idx (Tensor[B, N, k]) neighbour indices (any value where not valid);
            valid (Tensor[B, N, k] bool): the slots that are points.

        Returns:
            Tensor[B, channels, N]; zeros where a point has no valid slot.
        """
        B, N, k = idx.shape
        with validation(False):
            nb = gather(xyz, idx.clamp(min=-1, max=max(N - 1, -1)))  # (B, N, k, 3); padded slots read anything
        centre = xyz.unsqueeze(2).expand(B, N, k, 3)
        edges = torch.cat([centre, nb - centre], dim=-1)  # (B, N, k, 6)
        if not self.training:  # BatchNorm's running statistics: every edge apart, padding masked after the MLP
            h = self.mlp(edges.reshape(B, N * k, 6).transpose(1, 2)).view(B, self.channels, N, k)
            pooled = h.masked_fill(~valid.unsqueeze(1), -math.inf).amax(dim=3)  # (B, C, N)
            return torch.where(valid.any(dim=2).unsqueeze(1), pooled, torch.zeros_like(pooled))
        h = self.mlp(edges[valid].t().unsqueeze(0)).squeeze(0).t()  # (V, C): real edges only (BatchNorm statistics)
        full = h.new_full((B, N, k, self.channels), -math.inf)
        full = full.index_put((valid,), h)
        pooled = full.amax(dim=2)  # (B, N, C)
        pooled = torch.where(valid.any(dim=2, keepdim=True), pooled, torch.zeros_like(pooled))
        return pooled.transpose(1, 2)


class SamplingHead(nn.Module):
    """The sampling matrix's logits: ``concat(F, xyz)`` -> 1x1 conv (in -> in) + BN -> 1x1 conv (in -> m)
    + BN, per point (the issue's layers; ``activation=True`` adds a LeakyReLU(0.2) between the two, ours:
    without it the two layers compose to one affine map at inference).

    Padded points (``mask`` False) are left out of the computation, BatchNorm statistics included, and
    get ``-inf`` logits, so the softmax over ``N`` gives them probability 0.
    """

    def __init__(self, in_channels: int, num_out: int, activation: bool = False):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv1d(in_channels, in_channels, 1), nn.BatchNorm1d(in_channels)]
        if activation:
            layers.append(nn.LeakyReLU(0.2))
        layers += [nn.Conv1d(in_channels, num_out, 1), nn.BatchNorm1d(num_out)]
        self.layers = nn.Sequential(*layers)
        self.num_out = num_out

    def forward(self, x: Tensor, mask: Optional[Tensor] = None) -> Tensor:
        """Args: x (Tensor[B, in, N]); mask (Tensor[B, N] bool, optional). Returns: Tensor[B, m, N]."""
        if mask is None:
            return self.layers(x)
        h = self.layers(x.transpose(1, 2)[mask].t().unsqueeze(0)).squeeze(0).t()  # (V, m)
        B, _, N = x.shape
        out = h.new_full((B, N, self.num_out), -math.inf).index_put((mask,), h)
        return out.transpose(1, 2)


class AnchoredHead(nn.Module):
    """Ours (not the paper's): a sampling matrix whose ``m`` rows are anchored at the cloud's farthest point
    samples, so that its picks start spread out and cannot collapse onto a few points.

    Row ``i`` is a distribution over the ``candidates`` nearest points of anchor ``a_i`` (:func:`lidarops.fps`
    of the cloud; the anchor is its own nearest candidate) with logits

        ``-d(a_i, j)^2 / (s^2 exp(log_scale)) + <q(F_a_i), k(F_j)> / sqrt(qk) + u(F_j)``

    (``s^2`` the cloud's mean squared candidate distance, detached; ``q``, ``k``, ``u`` 1x1 convolutions of a
    shared 1x1 conv + BN + LeakyReLU(0.2) of ``concat(F, xyz)``). ``k`` and ``u`` start at zero, so an
    untrained head picks each anchor itself: farthest point sampling; training moves a pick to a
    neighbour the task prefers. The rows have no fixed count: ``m`` is chosen per call, so one model
    serves any cloud size and ratio (the paper's head fixes ``m`` by its last layer's width).
    Points off a row's candidate list get ``-inf`` logits (probability 0).
    """

    def __init__(self, in_channels: int, candidates: int = 16, hidden: int = 64, qk_channels: int = 16):
        super().__init__()
        self.candidates = positive_int(candidates, "candidates")
        self.hidden = nn.Sequential(nn.Conv1d(in_channels, hidden, 1, bias=False), nn.BatchNorm1d(hidden),
                                    nn.LeakyReLU(0.2))
        self.query = nn.Conv1d(hidden, qk_channels, 1)
        self.key = nn.Conv1d(hidden, qk_channels, 1)
        self.score = nn.Conv1d(hidden, 1, 1)
        self.log_scale = nn.Parameter(torch.zeros(()))
        for layer in (self.key, self.score):  # the untrained head is farthest point sampling
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)
        self.qk_channels = qk_channels

    def forward(self, x: Tensor, xyz: Tensor, lengths: Tensor, num_out: int,
                mask: Optional[Tensor] = None) -> Tensor:
        """Args: x (Tensor[B, in, N]); xyz (Tensor[B, N, 3]); lengths (Tensor[B]); num_out (int) ``m``;
        mask (Tensor[B, N] bool, optional). Returns: logits Tensor[B, m, N], ``-inf`` off each row's
        candidates (a cloud of fewer than ``m`` points repeats its anchors cyclically)."""
        logits, cand = self.sparse(x, xyz, lengths, num_out, mask)
        dense = logits.new_full((x.shape[0], num_out, x.shape[2]), -math.inf)
        # amax: a padded slot (-inf, clamped to point 0) never overrides a real candidate at point 0
        return dense.scatter_reduce(2, cand, logits, reduce="amax", include_self=True)

    def search(self, xyz: Tensor, lengths: Tensor, num_out: int) -> tuple[Tensor, Tensor, Tensor]:
        """The rows' anchors and candidates, from the points alone: ``(anchors (B, m), candidates (B, m, K)
        int64, their squared distances to the anchor (B, m, K))``, candidates ``-1`` (distance ``inf``) at a
        list's padding (a cloud of fewer than ``m`` points repeats its anchors cyclically)."""
        anchors = self.anchors(xyz, lengths, num_out)
        with validation(False), torch.no_grad():
            xyz = xyz.detach()
            d2, cand = knn(gather(xyz, anchors), xyz, min(self.candidates, xyz.shape[1]), None, lengths)
        return anchors, cand, d2

    def anchors(self, xyz: Tensor, lengths: Tensor, num_out: int) -> Tensor:
        """The rows' anchors (B, m) int64: farthest point samples, repeated cyclically past a cloud's size."""
        with validation(False), torch.no_grad():
            anchors = fps(xyz.detach(), num_out, lengths)  # (B, m), -1 past a cloud's size
            pos = torch.arange(num_out, device=xyz.device).unsqueeze(0)
            return torch.where(anchors >= 0, anchors, anchors.gather(1, pos % lengths.clamp(min=1).unsqueeze(1)))

    def neighbours(self, xyz: Tensor, lengths: Tensor) -> tuple[Tensor, Tensor]:
        """Every point's candidates, as :meth:`search` would find them were it an anchor: ``(candidates
        (B, N, K), squared distances (B, N, K))`` (the same kNN, queried at the same coordinates)."""
        with validation(False), torch.no_grad():
            xyz = xyz.detach()
            d2, cand = knn(xyz, xyz, min(self.candidates, xyz.shape[1]), lengths, lengths)
        return cand, d2

    def project(self, x: Tensor, mask: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor]:
        """The per-point terms of :meth:`logits`: ``(q, k, u)``, each ``(B, N, channels)`` (``u``: one channel)."""
        B, _, N = x.shape
        if mask is None or not self.training:  # eval: running statistics, padding rows never read below
            z = self.hidden(x)
        else:  # BatchNorm statistics of the valid points only
            h = self.hidden(x.transpose(1, 2)[mask].t().unsqueeze(0)).squeeze(0).t()
            z = h.new_zeros(B, N, h.shape[1]).index_put((mask,), h).transpose(1, 2)
        return self.query(z).transpose(1, 2), self.key(z).transpose(1, 2), self.score(z).transpose(1, 2)

    def project_rows(self, feats: Tensor) -> Tensor:
        """:meth:`project` in eval mode without padding, on rows: ``feats (B, N, in)`` -> the terms packed as
        ``(B, N, 2 qk + 1)`` (``q``, ``k``, ``u``), BatchNorm folded into the hidden layer."""
        wh, bh, wo, bo = folded.cached(self, "rows", folded.compute_dtype(feats), lambda: (
            *folded.conv_bn(self.hidden[0], self.hidden[1]),
            *(torch.cat(t) for t in zip(*(folded.conv_bn(c) for c in (self.query, self.key, self.score))))))
        return F.linear(F.leaky_relu(F.linear(feats, wh, bh), 0.2, inplace=True), wo, bo)

    def logits(self, terms: "tuple[Tensor, Tensor, Tensor] | Tensor", found: tuple[Tensor, Tensor, Tensor],
               padded: bool = True) -> tuple[Tensor, Tensor]:
        """The logits of :meth:`project`'s ``terms`` (or :meth:`project_rows`' packed ones) on :meth:`search`'s
        candidates: ``(logits (B, m, K), candidates (B, m, K))``, ``-inf`` logits at padding slots (whose
        candidate index is 0). The distances are the search's (no gradient reaches the points through them; the
        scale's parameter gets its own). ``padded=False``: the caller knows no list has a padding slot."""
        anchors, cand, d2 = found
        qk, B = self.qk_channels, cand.shape[0]
        if padded:
            valid = cand >= 0
            cand = cand.clamp(min=0)
            d2 = torch.where(valid, d2, 0.0)
            scale = d2.sum(dim=(1, 2)) / valid.sum(dim=(1, 2)).clamp(min=1)
        else:
            scale = d2.mean(dim=(1, 2))
        scale = scale.clamp(min=torch.finfo(d2.dtype).tiny).view(B, 1, 1) * self.log_scale.exp()
        with validation(False):
            if isinstance(terms, Tensor):  # packed rows: one gather per index set
                q = gather(terms, anchors)[..., :qk]  # (B, m, qk)
                k = gather(terms, cand)  # (B, m, K, 2 qk + 1)
                k, u = k[..., qk:2 * qk], k[..., 2 * qk]
            else:
                q = gather(terms[0], anchors)  # (B, m, qk)
                k = gather(terms[1], cand)  # (B, m, K, qk)
                u = gather(terms[2], cand).squeeze(-1)  # (B, m, K)
        logits = -d2 / scale + (k * q.unsqueeze(2)).sum(-1) / math.sqrt(qk) + u
        return (logits.masked_fill(~valid, -math.inf) if padded else logits), cand

    def sparse(self, x: Tensor, xyz: Tensor, lengths: Tensor, num_out: int,
               mask: Optional[Tensor] = None, found: Optional[tuple[Tensor, Tensor, Tensor]] = None
               ) -> tuple[Tensor, Tensor]:
        """:meth:`forward`'s logits on the candidates only: ``(logits (B, m, K), candidates (B, m, K) int64)``,
        ``-inf`` logits at padding slots (whose candidate index is 0). ``found``: :meth:`search`'s answer for
        these points and ``num_out``, if the caller already has it."""
        terms = self.project(x, mask)
        return self.logits(terms, self.search(xyz, lengths, num_out) if found is None else found)


class CASNet(nn.Module):
    """CAS-Net: ``m`` points out of each cloud, chosen by attention (issue 37).

    Args:
        num_out (int): ``m``, the points sampled per cloud (fixed by the head's last layer). The input's
            ``N`` is free; the paper uses ``N = m * D`` for a sampling ratio ``D`` (segments padded to it).
        k (int): neighbours per point (32 for detection; the fast variant 1).
        radius (float): ball query radius in metres (2.0 for detection).
        neighbors (str): ``"ball"`` (the paper) or ``"knn"``.
        num_oa_layers (int): offset-attention layers (3; the fast variant 1).
        channels (int), qk_channels (int): the embedding width (64) and the attention's query/key width (16).
        temperature (float): the logits are divided by it before the softmax (> 0; settable between steps).
        mode (str): default ``"hard"`` (AHSN, a subset of the input, as in every experiment of the paper) or
            ``"soft"`` (ASSN).
        dedup (bool): default for :meth:`forward`: reassign repeated picks (see the module docstring).
        head_activation (bool): a LeakyReLU between the head's two layers (not in the issue's recipe).
        chunk: each :class:`OffsetAttention`'s path: ``"auto"`` (plain for small inputs, blocks of query
            rows that never hold N x N for large ones; on CUDA without a gradient, torch's fused kernels for
            large ones), ``None`` (plain), an int (rows per block) or ``"fused"``
            (torch's fused attention kernels; the flash kernels under float16 autocast on CUDA).
        head (str): ``"matrix"`` (the paper's :class:`SamplingHead`, ``m`` fixed by its last layer) or
            ``"anchored"`` (ours, :class:`AnchoredHead`: rows anchored at farthest point samples; ``m``
            free per call, ``num_out`` its default).
        candidates (int): the anchored head's candidates per row (16).

    Attributes: ``embedding`` (:class:`FeatureEmbedding`), ``attention`` (``nn.ModuleList`` of
    :class:`OffsetAttention`), ``head`` (:class:`SamplingHead` or :class:`AnchoredHead`), ``head_kind``.
    """

    def __init__(self, num_out: int, k: int = 32, radius: float = 2.0, neighbors: str = "ball",
                 num_oa_layers: int = 3, channels: int = 64, qk_channels: int = 16, temperature: float = 1.0,
                 mode: str = "hard", dedup: bool = False, head_activation: bool = False,
                 chunk: "int | str | None" = "auto", head: str = "matrix", candidates: int = 16):
        super().__init__()
        self.num_out = positive_int(num_out, "num_out")
        num_oa_layers = positive_int(num_oa_layers, "num_oa_layers")
        # what a checkpoint records to rebuild the model (``model_config``)
        self.config = dict(num_out=num_out, k=k, radius=radius, neighbors=neighbors, num_oa_layers=num_oa_layers,
                           channels=channels, qk_channels=qk_channels, temperature=temperature, mode=mode,
                           dedup=dedup, head_activation=head_activation, chunk=chunk)
        if head not in _HEADS:
            raise ValueError(f"head must be one of {list(_HEADS)}, got {head!r}")
        if head != "matrix":  # older checkpoints' configs stay as they were
            self.config.update(head=head, candidates=candidates)
        self.head_kind = head
        qk_channels = positive_int(qk_channels, "qk_channels")
        if mode not in _MODES:
            raise ValueError(f"mode must be one of {list(_MODES)}, got {mode!r}")
        self.mode = mode
        self.dedup = flag(dedup, "dedup")
        self.temperature = temperature  # checked by the property
        self.embedding = FeatureEmbedding(k, radius, neighbors, channels)
        self.attention = nn.ModuleList([OffsetAttention(channels, qk_channels, chunk=chunk)
                                        for _ in range(num_oa_layers)])
        if head == "matrix":
            self.head = SamplingHead(channels * num_oa_layers + 3, self.num_out,
                                     flag(head_activation, "head_activation"))
        else:
            self.head = AnchoredHead(channels * num_oa_layers + 3, candidates, channels, qk_channels)

    @classmethod
    def fast(cls, num_out: int, **kwargs: Any) -> "CASNet":
        """The paper's fast variant: one offset-attention layer and ``k = 1`` (each point's own edge
        ``[p, 0]``: the nearest neighbour, as ball query's first in-radius point is any nearby point)."""
        kwargs = {"k": 1, "neighbors": "knn", "num_oa_layers": 1, **kwargs}
        return cls(num_out, **kwargs)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config: Optional[dict] = None, map_location: Any = "cpu",
                        check_finite: bool = True) -> "CASNet":
        """A CAS-Net from a file of :meth:`save` (or any checkpoint recording ``model_class: "CASNet"``, its
        keyword arguments as ``model_config`` and ``model_state``). For the CAS-Net inside a trained
        ``CASNetPointNet`` or ``CASNetPointPillars`` checkpoint use :func:`load_casnet`."""
        from lidarops.checkpoint import CheckpointError, model_state, read_checkpoint
        from lidarops.checkpoint import check_finite as refuse_non_finite
        from lidarops.models.base import placed

        ckpt = read_checkpoint(path, map_location)
        name = ckpt.get("model_class")
        if name not in (None, cls.__name__):
            raise CheckpointError(f"{path} holds a {name}, not a CASNet: load it with "
                                  "lidarops.models.casnet.load_casnet(path)")
        config = ckpt.get("model_config") if config is None else config
        if not isinstance(config, dict):
            raise CheckpointError(f"{path}: no model_config dict (CASNet's keyword arguments) in the file")
        try:
            model = cls(**config)
        except (TypeError, ValueError) as e:
            raise CheckpointError(f"{path}: model_config does not fit CASNet: {e}") from None
        state = model_state(ckpt, str(path))
        if check_finite:
            refuse_non_finite(state, str(path))
        own = model.state_dict()
        try:
            model.load_state_dict({k: v.to(own[k].dtype) if k in own else v for k, v in state.items()})
        except RuntimeError as e:
            raise CheckpointError(f"{path}: its weights do not fit its model_config: "
                                  f"{str(e).splitlines()[0]}") from None
        return placed(model, map_location)

    def save(self, path: "str | Path", **extra: Any) -> Path:
        """Writes ``{model_class: "CASNet", model_config, model_state, ...extra}`` (a lidarops checkpoint
        file; ``extra`` e.g. the task model it was trained for and its evaluation)."""
        from lidarops.checkpoint import format_fields, save_checkpoint

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu() for k, v in self.state_dict().items()}
        # the settable attributes as they are now
        config = dict(self.config, temperature=self.temperature, mode=self.mode, dedup=self.dedup)
        save_checkpoint({**format_fields(), "model_class": "CASNet", "model_config": config,
                         "model_state": state, **extra}, [path])
        return path

    @property
    def temperature(self) -> float:
        return self._temperature

    @temperature.setter
    def temperature(self, value: float) -> None:
        self._temperature = real(value, "temperature", 0.0, lo_open=True)

    def forward(self, points: Tensor, lengths: Optional[Tensor] = None, mode: Optional[str] = None,
                dedup: Optional[bool] = None, num_out: Optional[int] = None) -> CASNetOutput:
        """Sample ``m`` points of each cloud.

        Args:
            points (Tensor[B, N, C]): floating point, ``C >= 3`` with ``x, y, z`` first, on the model's
                device; only ``x, y, z`` enter the network (in the parameters' dtype), every channel is
                sampled (in ``points``' dtype).
            lengths (Tensor[B], optional): valid points per cloud, in ``[1, N]`` (padding rows are ignored:
                neither neighbours, attention keys nor candidates).
            mode (str, optional): ``"hard"`` or ``"soft"``; default the model's.
            dedup (bool, optional): reassign repeated picks (hard mode); default the model's.
            num_out (int, optional): ``m`` for this call (the anchored head only; default ``self.num_out``).

        Returns:
            :class:`CASNetOutput`.

        Raises:
            ValueError: naming ``points``, ``lengths``, ``mode``, ``dedup`` or ``num_out``.
        """
        mode = self.mode if mode is None else mode
        if mode not in _MODES:
            raise ValueError(f"mode must be one of {list(_MODES)}, got {mode!r}")
        dedup = self.dedup if dedup is None else flag(dedup, "dedup")
        num_out = self._num_out(num_out)
        full = lengths is None
        lengths = self._check_input(points, lengths)
        h, xyz, mask = self._features(points, lengths, full)
        if self.head_kind == "matrix":
            logits = self.head(h, mask) / self.temperature
        else:
            logits = self.head(h, xyz, lengths, num_out, mask) / self.temperature
        sampled, indices, soft = matrix_sample(logits, points, mode=mode, dedup=dedup, mask=mask)
        return CASNetOutput(sampled=sampled, indices=indices, soft_matrix=soft, logits=logits, lengths=lengths,
                            num_duplicates=None if indices is None else count_duplicates(indices), mode=mode)

    def _num_out(self, num_out) -> int:
        if num_out is None or (self.head_kind == "matrix" and num_out == self.num_out):
            return self.num_out
        if self.head_kind == "matrix":
            raise ValueError(f"num_out={num_out!r}: the paper's head gives num_out={self.num_out} rows, fixed by its "
                             "last layer (head='anchored' takes any num_out)")
        return check_positive_int(num_out, "num_out")

    def _features(self, points: Tensor, lengths: Tensor, full: bool = False) -> tuple[Tensor, Tensor, Optional[Tensor]]:
        """``(concat(attention features, xyz) (B, C, N), xyz (B, N, 3) in the parameters' dtype, mask or None)``
        of checked points; ``full``: the caller knows every cloud fills ``N`` (no host read to find out)."""
        xyz, mask = self._xyz(points, lengths, full)
        return self._attend(xyz, lengths, mask), xyz, mask

    def _xyz(self, points: Tensor, lengths: Tensor, full: bool = False) -> tuple[Tensor, Optional[Tensor]]:
        B, N, _ = points.shape
        mask = None
        if not full and bool((lengths < N).any()):
            mask = torch.arange(N, device=points.device).unsqueeze(0) < lengths.unsqueeze(1)
        dtype = next(self.parameters()).dtype
        xyz = points[..., :3].to(dtype)
        if mask is not None:  # padding rows may hold anything: never let them reach a product
            xyz = xyz.masked_fill(~mask.unsqueeze(-1), 0)
        return xyz, mask

    def _attend(self, xyz: Tensor, lengths: Tensor, mask: Optional[Tensor]) -> Tensor:
        x = self.embedding(xyz, lengths)
        feats = []
        for layer in self.attention:
            x = layer(x) if mask is None else layer(x, mask=mask)
            feats.append(x)
        return torch.cat(feats + [xyz.transpose(1, 2)], dim=1)

    def _attend_rows(self, xyz: Tensor, lengths: Tensor) -> Tensor:
        """:meth:`_attend` in eval mode for clouds that fill ``N``, as rows ``(B, N, C)`` with BatchNorm folded
        (fewer launches; the same values up to rounding)."""
        x = self.embedding.rows(xyz, lengths)
        feats = []
        for layer in self.attention:
            x = layer.rows(x)
            feats.append(x)
        return torch.cat(feats + [xyz.to(x.dtype)], dim=-1)

    @torch.no_grad()
    def pick(self, points: Tensor, lengths: Optional[Tensor] = None, num_out: Optional[int] = None,
             dedup: Optional[bool] = None) -> Tensor:
        """The hard picks alone (inference): :meth:`forward`'s ``indices`` in hard mode, without its
        ``(B, m, N)`` matrices where the head allows. The anchored head scores each row's candidates only
        (memory ``O(m K)`` instead of ``O(m N)``), with the same picks as :meth:`forward` (ties included;
        distinct picks: the same greedy on the same pairs, up to the rounding of the log-softmax).

        Args: as :meth:`forward` (``mode`` is hard). Returns: Tensor[B, m] int64.
        """
        dedup = self.dedup if dedup is None else flag(dedup, "dedup")
        if self.head_kind == "matrix":
            return self.forward(points, lengths, mode="hard", dedup=dedup, num_out=num_out).indices
        num_out = self._num_out(num_out)
        full = lengths is None
        lengths = self._check_input(points, lengths)
        xyz, mask = self._xyz(points, lengths, full)
        side = _side_stream(points.device)
        if side is not None:
            # farthest point sampling is sequential and holds a few SMs for most of the call: it runs on a second
            # stream, while this one finds every point's candidates (any anchor's list is then its row) and
            # computes the features
            main = torch.cuda.current_stream(points.device)
            side.wait_stream(main)
            with torch.cuda.stream(side):
                anchors = self.head.anchors(xyz, lengths, num_out)
            near = self.head.neighbours(xyz, lengths)
            terms = self._terms(xyz, lengths, mask)
            main.wait_stream(side)
            anchors.record_stream(main)  # made on the side stream, read on this one
            with validation(False):
                found = (anchors, gather(near[0], anchors), gather(near[1], anchors))
        else:
            terms = self._terms(xyz, lengths, mask)
            found = self.head.search(xyz, lengths, num_out)
        N = points.shape[1]
        # no padding slot: every cloud fills N (no lengths given) and has the K candidates a row asks for
        padded = not full or N < self.head.candidates
        logits, cand = self.head.logits(terms, found, padded)
        logits = logits / self.temperature
        # forward's argmax over N: the lowest point among a row's best candidates
        best = logits.amax(dim=-1, keepdim=True)
        plain = torch.where(logits == best, cand, N).amin(dim=-1)
        if not dedup:
            return plain
        return _greedy_candidates(torch.log_softmax(logits, dim=-1), cand, plain, N, padded)

    def _terms(self, xyz: Tensor, lengths: Tensor, mask: Optional[Tensor]):
        """The anchored head's per-point terms: on CUDA in eval mode without padding packed rows (fewer launches,
        which bound the call there), else :meth:`project`'s (on the CPU its layout rounds alike points alike, so
        exact ties stay ties as in :meth:`forward`)."""
        if mask is None and not self.training and xyz.is_cuda:
            return self.head.project_rows(self._attend_rows(xyz, lengths))
        return self.head.project(self._attend(xyz, lengths, mask), mask)

    def _check_input(self, points, lengths) -> Tensor:
        check_tensor(points, "points")
        if points.dim() != 3 or points.shape[-1] < 3 or points.shape[0] == 0 or points.shape[1] == 0:
            raise ValueError(f"points must be (B, N, C) with B, N >= 1 and C >= 3 (x, y, z first), got "
                             f"{describe(points)}")
        if not points.is_floating_point():
            raise ValueError(f"points must be floating point, got {describe(points)}")
        device = next(self.parameters()).device
        if points.device != device:
            raise ValueError(f"points is on {points.device} but the model is on {device}; move one of them")
        given = lengths
        lengths = lengths_or_full(lengths, points, "lengths")
        if value_checks_enabled():
            n = points.shape[1]
            ranged = [] if given is None or not lengths.numel() else \
                [(lengths, 1, n, lambda: f"lengths must lie in [1, {n}] (a cloud needs a point to sample from), "
                                         f"got {lengths.tolist()}")]
            xyz = points[..., :3] if given is None else _valid_rows(points[..., :3], lengths)
            check_values(coords=[(xyz, "points")], ranged=ranged)
        return lengths


_SIDE_STREAMS: dict = {}


def _side_stream(device: torch.device) -> "Optional[torch.cuda.Stream]":
    """A second CUDA stream of ``device`` (one per device, made once), None off CUDA."""
    if device.type != "cuda":
        return None
    index = device.index if device.index is not None else torch.cuda.current_device()
    if index not in _SIDE_STREAMS:
        _SIDE_STREAMS[index] = torch.cuda.Stream(index)
    return _SIDE_STREAMS[index]


def _valid_rows(xyz: Tensor, lengths: Tensor) -> Tensor:
    """The coordinates of the valid rows only (padding rows may hold anything), flattened."""
    N = xyz.shape[1]
    if N == 0:
        return xyz.reshape(-1, 3)
    mask = torch.arange(N, device=xyz.device).unsqueeze(0) < lengths.clamp(0, N).unsqueeze(1)
    return xyz[mask]


def count_duplicates(indices: Tensor) -> Tensor:
    """Tensor[B] int64: per row of ``indices (B, m)``, ``m`` minus its distinct entries (-1 ignored)."""
    s = torch.sort(indices, dim=1).values
    return ((s[:, 1:] == s[:, :-1]) & (s[:, 1:] >= 0)).sum(dim=1)


def matrix_sample(logits: Tensor, features: Tensor, mode: str = "hard", dedup: bool = False,
                  mask: Optional[Tensor] = None) -> tuple[Tensor, Optional[Tensor], Tensor]:
    """Sample per-point features with the matrix the logits define.

    ``S~ = softmax(logits, dim=-1)``. Soft: ``S~ @ features``. Hard: each row's argmax (ties to the lower
    index; :func:`greedy_distinct_rows` with ``dedup``), the rows ``features[b, indices[b]]`` exactly, and
    in backward the straight-through estimator ``S - stopgrad(S~) + S~``: the gradient reaching ``S~``
    (and so the logits) is the one soft mode would get for the same upstream gradient, ``g @ features^T``,
    and ``features`` gets the one-hot rows' ``S^T g``. Computed as ``gather(features, indices) + (y -
    stopgrad(y))`` with ``y = S~ @ stopgrad(features)``: forward adds an exact zero, so the hard output is
    bit-for-bit a subset of the input (``S @ features`` with a float ``S`` would round); the soft product is
    only formed when a gradient is needed.

    Args:
        logits (Tensor[B, m, N]): already divided by the temperature; ``-inf`` where ``mask`` is False.
        features (Tensor[B, N, C]): what is sampled; padded rows (``mask`` False) may hold anything.
        mode (str): ``"hard"`` or ``"soft"``.
        dedup (bool): hard mode: distinct picks where the cloud allows.
        mask (Tensor[B, N] bool, optional): the valid points.

    Returns:
        ``(sampled (B, m, C), indices (B, m) int64 or None in soft mode, soft matrix (B, m, N))``.
    """
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {list(_MODES)}, got {mode!r}")
    soft = torch.softmax(logits, dim=-1)
    safe = features if mask is None else features.masked_fill(~mask.unsqueeze(-1), 0)
    if mode == "soft":
        return torch.bmm(soft.to(safe.dtype), safe), None, soft
    if dedup:
        indices = greedy_distinct_rows(torch.log_softmax(logits.detach(), dim=-1), mask)
    else:
        indices = torch.argmax(logits.detach(), dim=-1)
    with validation(False):  # argmax indices are in range
        sampled = gather(features, indices)
    if torch.is_grad_enabled() and soft.requires_grad:
        y = torch.bmm(soft.to(safe.dtype), safe.detach())
        sampled = sampled + (y - y.detach())
    return sampled, indices, soft


def greedy_distinct_rows(scores: Tensor, mask: Optional[Tensor] = None) -> Tensor:
    """Distinct picks for the rows of a sampling matrix: the greedy assignment by decreasing score.

    The (row, point) pairs are taken in decreasing ``scores`` order (ties: lower row, then lower point),
    each assigned unless its row is assigned or its point taken. Rows left without a free point (a cloud
    with fewer valid points than rows) keep their plain argmax, a repeat.

    Computed per cloud on candidate lists: each row's ``K`` best points (a stable sort on the device), the
    ``m K`` pairs scanned in order on the host (:func:`lidarops.ops.greedy_assign`, C++) until every row that
    can be served is. If that happens within the lists, the result is the greedy of the whole matrix (a row
    assigned within its list was assigned before any pair beyond it could come up); otherwise ``K`` grows
    fourfold and the scan restarts (``K = N`` is the whole matrix; also from the start when the cloud has
    fewer valid points than rows), unless no row has a finite score beyond its ``K`` (rows of few candidates:
    the lists then hold every pair). ``K`` starts at 32: rows that disagree finish at once; alike rows (an
    untrained or a collapsed model) need ``K`` up to ``N``.

    Args:
        scores (Tensor[B, m, N]): comparable across rows (log-probabilities of each row's distribution);
            ``-inf`` marks a point that may not be picked.
        mask (Tensor[B, N] bool, optional): the points that may be picked.

    Returns:
        Tensor[B, m] int64.
    """
    B, m, N = scores.shape
    s = scores.detach()
    if mask is not None:
        s = s.masked_fill(~mask.unsqueeze(1), -math.inf)
    out = torch.argmax(s, dim=-1)  # rows left unserved keep it
    if m == 0 or N == 0:
        return out
    values, points = torch.sort(s, dim=2, descending=True, stable=True)  # ties: the lower point first
    picks = out.cpu()
    for b in range(B):
        valid = int(torch.isfinite(s[b]).any(dim=0).sum())  # points some row may take
        can_serve = min(m, valid)
        k = min(N, 32) if valid >= m else N  # fewer points than rows: which rows go unserved needs all pairs
        while True:
            vals = values[b, :, :k].reshape(-1)
            order = torch.sort(vals, descending=True, stable=True).indices  # ties: row-major (lower row first)
            offered = int(torch.isfinite(vals).sum())  # -inf pairs (padding) sort last and are never taken
            order = order[:offered]
            # on the host: dense lists of alike rows (an untrained or collapsed model) would take one round per
            # row on the device
            assign = greedy_assign((order // k).cpu(), points[b, :, :k].reshape(-1)[order].cpu(), m, N, can_serve)
            served = int((assign >= 0).sum())
            # rows whose lists end within k (sparse rows: the anchored head) have offered every pair they have
            exhausted = k == N or not bool(torch.isfinite(values[b, :, k]).any())
            if served == can_serve or exhausted:
                break
            k = min(N, 4 * k)
        picks[b] = torch.where(assign >= 0, assign, picks[b])
    return picks.to(scores.device)


def _greedy_candidates(scores: Tensor, cand: Tensor, plain: Tensor, num_points: int, padded: bool = True) -> Tensor:
    """:func:`greedy_distinct_rows` on sparse rows: ``scores (B, m, K)`` of the points ``cand (B, m, K)`` (``-inf``
    at padding). Pairs in the order the dense greedy takes them (decreasing score; ties: lower row, then lower
    point); rows left without a free candidate keep ``plain``. On the scores' device, without a host read: the
    clouds are one list (rows and points offset per cloud), and the padding pairs, ranked last, offer each
    cloud's one extra point (the first row to take it had no free candidate left, the later ones find it taken).
    ``padded=False``: the caller knows there is no padding slot (fewer steps)."""
    from lidarops import extension

    B, m, K = scores.shape
    if B * m * K == 0:
        return plain
    by_point = torch.sort(cand, dim=2, stable=True)  # within a row, ties of score: the lower point first
    vals = scores.gather(2, by_point.indices).view(B, m * K)
    order = torch.sort(vals, dim=1, descending=True, stable=True).indices  # ties: lower row, then lower point
    cols = by_point.values.view(B, m * K).gather(1, order)
    if padded:
        cols = torch.where(torch.isfinite(vals.gather(1, order)), cols, num_points)
    rows = order // K
    if B > 1:
        base = torch.arange(B, device=scores.device).unsqueeze(1)
        rows, cols = rows + base * m, cols + base * (num_points + 1)
    extension.load()
    # the raw op: pairs in range by construction (the wrapper would check them with a host read)
    assign = torch.ops.lidarops.greedy_assign(rows.view(-1), cols.view(-1), B * m, B * (num_points + 1), B * m)
    assign = assign.view(B, m)
    if B > 1:
        assign = assign - base * (num_points + 1)
    keep = (assign >= 0) & (assign < num_points) if padded or B > 1 else assign >= 0
    return torch.where(keep, assign, plain)


@torch.no_grad()
def segment_and_sample(model: CASNet, points: Tensor, ratio: int, max_points: int = 8192,
                       num_samples: Optional[int] = None, dedup: Optional[bool] = None) -> Tensor:
    """Sample a cloud of any size with a CAS-Net, segment by segment, as the paper does (inference).

    The model's head fixes ``m = model.num_out``, so a segment holds ``N = m * ratio`` points: the
    cloud's ``n`` points are cut into ``ceil(n / N)`` spatially coherent segments of balanced size
    (:func:`lidarops.models.samplers.spatial_segments`), each padded to ``N`` rows and masked (padding
    rows are no neighbours, no attention keys and no candidates), all segments in one batched forward
    (hard mode). Every segment gives ``m`` picks, so the effective ratio is ``n / (segments * m) <= ratio``;
    ``num_samples`` keeps exactly that many instead: per segment its share (proportional to its size,
    :func:`~lidarops.models.samplers.segment_shares`, at most ``min(m, segment size)``), the most confident
    rows (largest ``S~`` at their pick) first, preferring rows whose point is not kept yet. The anchored head
    (whose row count is free) is run with as many rows as the largest share, and each segment keeps its first
    ``share`` rows: the ones anchored at its first farthest point samples.

    Args:
        model (CASNet): in the mode you want (``eval()`` for inference: BatchNorm's running statistics).
        points (Tensor[n, C]): one cloud, ``x, y, z`` first, on the model's device.
        ratio (int): the sampling ratio ``D`` (segment size ``m * D``), with ``m * D <= max_points``.
        max_points (int): most points per segment (8,192 in the paper: offset attention is O(N^2)).
        num_samples (int, optional): how many to keep (default all ``segments * m``).
        dedup (bool, optional): passed to the model (default the model's).

    Returns:
        Tensor[K] int64: indices into ``points``, segment by segment (in the order of ``spatial_segments``),
        each segment's kept rows in row order. Segments are disjoint, so indices repeat only within one
        segment, and only when ``dedup`` is off (or a segment has fewer points than it gives).

    Raises:
        ValueError: naming ``points``, ``ratio``, ``max_points`` or ``num_samples``.
    """
    check_tensor(points, "points")
    if points.dim() != 2 or points.shape[-1] < 3 or not points.is_floating_point():
        raise ValueError(f"points must be one cloud (n, C), floating point, C >= 3, got {describe(points)}")
    ratio = check_positive_int(ratio, "ratio")
    max_points = check_positive_int(max_points, "max_points")
    m = model.num_out
    size = m * ratio
    if size > max_points:
        raise ValueError(f"ratio={ratio}: segments of num_out * ratio = {m} * {ratio} = {size} points, more than "
                         f"max_points={max_points}")
    if num_samples is not None:
        num_samples = check_positive_int(num_samples, "num_samples")
    n = points.shape[0]
    if n == 0:
        return torch.empty(0, dtype=torch.int64, device=points.device)
    segments = spatial_segments(points, size)
    sizes = [s.numel() for s in segments]
    batch = points.new_zeros(len(segments), size, points.shape[1])
    for i, seg in enumerate(segments):
        batch[i, :seg.numel()] = points[seg]
    lengths = torch.tensor(sizes, dtype=torch.int64, device=points.device)
    if model.head_kind == "anchored" and num_samples is not None:
        # rows come in farthest-point order, so each segment's first `share` rows are its best spread ones
        if num_samples > n:
            raise ValueError(f"num_samples={num_samples}: the cloud has only {n} points")
        shares = segment_shares(sizes, num_samples, caps=sizes)
        picks = model.pick(batch, lengths, num_out=max(shares), dedup=dedup)
        return torch.cat([seg[picks[i, :share]] for i, (seg, share) in enumerate(zip(segments, shares))])
    out = model(batch, lengths, mode="hard", dedup=dedup)
    picks = [seg[out.indices[i]] for i, seg in enumerate(segments)]
    if num_samples is None:
        return torch.cat(picks)
    if num_samples > len(segments) * m:
        raise ValueError(f"num_samples={num_samples}: the model gives at most {len(segments) * m} points of this "
                         f"cloud at ratio={ratio} ({len(segments)} segments of {m}); lower the ratio")
    shares = segment_shares(sizes, num_samples, caps=[min(m, s) for s in sizes])
    confidence = out.soft_matrix.gather(2, out.indices.unsqueeze(2)).squeeze(2)  # (segments, m)
    kept = []
    for i, share in enumerate(shares):
        order = torch.sort(-confidence[i], stable=True).indices.tolist()
        local = out.indices[i].tolist()
        seen, first, repeats = set(), [], []
        for r in order:
            (repeats if local[r] in seen else first).append(r)
            seen.add(local[r])
        rows = sorted((first + repeats)[:share])
        kept.append(picks[i][torch.tensor(rows, dtype=torch.int64, device=points.device)])
    return torch.cat(kept)


class CASNetSampler(Sampler):
    """A trained :class:`CASNet` behind the samplers' interface ``sampler(points, m, lengths=None)``.

    Each cloud goes through :func:`segment_and_sample` with ``num_samples = min(m, n)``. The ratio: the
    given one, or per cloud ``D = max(1, n // m)`` capped by ``max_points // model.num_out`` (so the
    segments give at least ``m`` rows); with ``dedup`` (default here) a cloud of ``n >= m`` points
    yields ``m`` distinct points (when balanced segments fall a few short, ``D`` is lowered until they
    do; at ``D = 1`` every point is kept), then -1 padding past ``n``. Without ``dedup`` picks may repeat.
    The model is used as it is (call ``model.eval()`` first for inference).

    Args:
        model (CASNet): the sampler.
        ratio (int, optional): a fixed sampling ratio (segments of ``num_out * ratio`` points); a cloud
            whose segments give fewer than ``m`` points is refused (``ValueError`` naming ``m``).
        max_points (int): most points per segment.
        dedup (bool): distinct picks.
        whole (bool): no segments: the whole cloud in one forward with ``m`` rows (the anchored head only,
            whose row count is free; offset attention over all ``n`` points, without ever holding n x n;
            :meth:`CASNet.pick`). With ``dedup``, a row whose candidates are all taken gets the free point
            nearest to its pick.
    """

    def __init__(self, model: CASNet, ratio: Optional[int] = None, max_points: int = 8192, dedup: bool = True,
                 whole: bool = False):
        if not isinstance(model, CASNet):
            raise ValueError(f"model must be a CASNet, got {type(model).__name__}")
        self.whole = flag(whole, "whole")
        if self.whole and model.head_kind != "anchored":
            raise ValueError("whole=True needs a CASNet with head='anchored' (the paper's head fixes m to its "
                             f"num_out={model.num_out}, so a whole cloud needs segments)")
        self.model = model
        self.ratio = None if ratio is None else check_positive_int(ratio, "ratio")
        self.max_points = check_positive_int(max_points, "max_points")
        if model.num_out > self.max_points:
            raise ValueError(f"max_points={self.max_points} is below the model's num_out={model.num_out}")
        self.dedup = flag(dedup, "dedup")

    def sample(self, points: Tensor, m: int, lengths: Tensor) -> Tensor:
        B = points.shape[0]
        out = torch.full((B, m), -1, dtype=torch.int64, device=points.device)
        cap = self.max_points // self.model.num_out
        for b, n in enumerate(lengths.tolist()):
            if n == 0:
                continue
            want = min(m, n)
            if self.whole:
                with validation(False):  # the points were checked above (the sampler's own checks)
                    idx = self.model.pick(points[b:b + 1, :n], num_out=want, dedup=self.dedup)[0]
                out[b, :want] = _fill_repeats(points[b, :n, :3], idx) if self.dedup else idx
                continue
            ratio = self.ratio if self.ratio is not None else min(max(1, n // m), cap)
            while True:
                segs = math.ceil(n / (self.model.num_out * ratio))
                if segs * self.model.num_out < want and self.ratio is not None:
                    raise ValueError(f"m={m}: at ratio={ratio} the model gives at most {segs * self.model.num_out} "
                                     f"points of cloud {b} ({n} points); lower the ratio or leave it to the sampler")
                idx = segment_and_sample(self.model, points[b, :n], ratio, self.max_points,
                                         num_samples=want, dedup=self.dedup)
                short = self.dedup and torch.unique(idx).numel() < want
                if not short or ratio == 1 or self.ratio is not None:
                    break
                ratio -= 1
            out[b, :idx.numel()] = idx
        return out

    def __repr__(self) -> str:
        return (f"CASNetSampler(ratio={self.ratio}, max_points={self.max_points}, dedup={self.dedup}, "
                f"whole={self.whole})")


def _fill_repeats(xyz: Tensor, idx: Tensor) -> Tensor:
    """``idx (m,)`` of the points ``xyz (n, 3)`` with each repeat (a row holding a point an earlier row holds) given
    instead the free point (held by no row) nearest to its pick, rows in order (float64 distances, ties to the lower
    index): distinct picks when ``m <= n``. One op on ``idx``'s device (``lidarops::fill_repeats``), no host read."""
    from lidarops import extension

    if idx.numel() == 0:
        return idx
    extension.load()
    xyz = xyz[:, :3].to(torch.float64 if xyz.dtype == torch.float64 else torch.float32).contiguous()
    return torch.ops.lidarops.fill_repeats(xyz, idx)


def casnet_loss(out: CASNetOutput, points: Tensor, task_loss: Tensor, alpha: float = 1.0, beta: float = 1.0,
                cosine_form: str = "paper") -> dict[str, Tensor]:
    """CAS-Net's training loss: ``task + alpha * Chamfer(sampled xyz, input xyz) + beta * cosine(S~)``.

    Args:
        out (CASNetOutput): the model's output for ``points``.
        points (Tensor[B, N, C]): the input (its valid rows, ``out.lengths``, enter the Chamfer distance).
        task_loss (Tensor): a scalar, e.g. the classifier's or the frozen detector's loss on ``out.sampled``.
        alpha, beta (float): >= 0 (1 and 1 in the paper).
        cosine_form (str): the cosine loss's form (``"paper"``: ``sum_{i != j} |cos|``; see
            :func:`lidarops.models.casnet_losses.selection_cosine_loss`).

    Returns:
        dict: ``loss`` (the total), ``loss_task``, ``loss_chamfer``, ``loss_cosine``.
    """
    if not isinstance(out, CASNetOutput):
        raise ValueError(f"out must be a CASNetOutput, got {type(out).__name__}")
    check_tensor(points, "points")
    if points.dim() != 3 or points.shape[-1] < 3 or points.shape[:2] != out.soft_matrix.shape[::2]:
        raise ValueError(f"points must be the (B, N, C) input of out (B, N = {tuple(out.soft_matrix.shape[::2])}), "
                         f"got {describe(points)}")
    check_tensor(task_loss, "task_loss")
    if task_loss.numel() != 1:
        raise ValueError(f"task_loss must be a scalar tensor, got {describe(task_loss)}")
    for name, v in (("alpha", alpha), ("beta", beta)):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    full = bool((out.lengths == points.shape[1]).all())
    chamfer = chamfer_distance(out.sampled_xyz, points[..., :3].to(out.sampled.dtype),
                               b_lengths=None if full else out.lengths)
    cosine = selection_cosine_loss(out.soft_matrix, form=cosine_form)
    task = task_loss.reshape(())
    return {"loss": task + alpha * chamfer + beta * cosine, "loss_task": task, "loss_chamfer": chamfer,
            "loss_cosine": cosine}


def load_casnet(source: "str | Path", device: Any = "cpu") -> CASNet:
    """The CAS-Net of a checkpoint, in eval mode on ``device``.

    Args:
        source: a shipped checkpoint's name (``lidarops.models.weights.available()``, e.g.
            ``"casnet_pointnet_d8"``) or a file: a CAS-Net of :meth:`CASNet.save`, or a ``lidarops train``
            checkpoint of a model holding one as ``.casnet`` (``CASNetPointNet``, ``CASNetPointPillars``).
        device: where the model goes.

    Raises:
        FileNotFoundError: neither a file nor a shipped name.
        lidarops.checkpoint.CheckpointError: a file that holds no CAS-Net, or weights that do not fit.
    """
    from lidarops.checkpoint import CheckpointError, read_checkpoint
    from lidarops.models import MODELS, model_class
    from lidarops.models import weights

    path = Path(source)
    if not path.is_file():
        if isinstance(source, str) and source in weights.available():
            path = weights.path(source)
        else:
            raise FileNotFoundError(f"CAS-Net checkpoint {source}: no such file, nor a shipped checkpoint "
                                    f"(shipped: {', '.join(weights.available()) or 'none'})")
    ckpt = read_checkpoint(path)
    name = ckpt.get("model_class")
    if name is None:  # a bare {model_config, state_dict} is a CASNet, unless its config is a task model's
        config = ckpt.get("model_config")
        name = "model that names no class (a detector's or classifier's config)" \
            if isinstance(config, dict) and "class_names" in config else "CASNet"
    if name == "CASNet":
        return CASNet.from_checkpoint(path).eval().to(device)
    if name in MODELS:
        cls = model_class(name)
        if hasattr(cls, "casnet_of_checkpoint"):
            return cls.casnet_of_checkpoint(path).eval().to(device)
    raise CheckpointError(f"{path} holds a {name}, which has no CAS-Net (CASNet, CASNetPointNet and "
                          "CASNetPointPillars checkpoints do)")
