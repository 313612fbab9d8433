"""CAS-Net's two sampling losses (Chen et al., ICME 2023; Rozsa et al. 2026): the Chamfer distance between the
sampled and the input cloud, and the cosine loss that keeps the rows of the soft selection matrix apart.

Where each form comes from:

* :func:`chamfer_distance`: squared L2 to the nearest neighbour, both directions, each averaged over its points
  and then added (issue 37: "squared L2, both directions averaged"; the reference code's ``get_cd_loss`` does the
  same: ``mean(dist_a) + mean(dist_b)`` with weights 1 and 1), averaged over the clouds of the batch.
* :func:`selection_cosine_loss`, ``form="paper"``: the paper's ``sum_{i != j} |cos(S_i, S_j)|`` over the rows of
  the soft matrix, divided here by the m (m - 1) ordered pairs (so it lies in [0, 1] and alpha = beta = 1 keeps it
  on the scale of a classification loss: the rows of a softmax are positive, so at initialisation every cosine is
  near 1 and the plain sum would be near m^2, about 10^6 for m = 1024), averaged over the batch. The plain sum is
  this value times m (m - 1).
* ``form="frobenius"``: what the CAS-Net reference code computes (``SLRS.forward`` in ``utils/slrsa_util.py`` of
  github.com/yuanhui0325/CAS-Net): the Frobenius norm of the cosine matrix with its diagonal zeroed,
  ``sqrt(sum_{i != j} cos_ij^2)``, not normalised, averaged over the batch. Both forms take
  ``cos_ij = <S_i, S_j> / (|S_i| |S_j| + 1e-10)`` as that code does.
"""
from __future__ import annotations

import torch
from torch import Tensor

from lidarops.ops.neighbors import knn
from lidarops.ops.validation import (
    check_cloud,
    check_same_device,
    check_tensor,
    check_values,
    describe,
    lengths_or_full,
    validation,
    value_checks_enabled,
)

__all__ = ["chamfer_distance", "selection_cosine_loss", "COSINE_FORMS"]

#: The forms of :func:`selection_cosine_loss`.
COSINE_FORMS = ("paper", "frobenius")
#: The reference code's constant in ``cos_ij = <S_i, S_j> / (|S_i| |S_j| + 1e-10)``.
COSINE_EPS = 1e-10


def chamfer_distance(a: Tensor, b: Tensor, a_lengths: "Tensor | None" = None,
                     b_lengths: "Tensor | None" = None) -> Tensor:
    """Symmetric Chamfer distance with squared Euclidean distances, each direction averaged over its points.

    For each cloud ``c`` of the batch, with ``n_a = a_lengths[c]`` and ``n_b = b_lengths[c]`` real points::

        cd_c = (1 / n_a) sum_i min_j |a_i - b_j|^2  +  (1 / n_b) sum_j min_i |b_j - a_i|^2

    and the result is the mean of ``cd_c`` over the batch. Points beyond a cloud's length are padding: they are
    neither matched nor matched to, and get zero gradient.

    Built on :func:`lidarops.knn` with k = 1 (its squared distances are differentiable in both clouds; at a tie
    the gradient goes to the lower-index neighbour, knn's tie rule).

    Args:
        a (Tensor[B, N, 3]), b (Tensor[B, M, 3]): float32/float64 (float16/bfloat16 computed in float32), one
            device.
        a_lengths, b_lengths (Tensor[B] integer, optional): real points per cloud, in [1, N] and [1, M];
            default N and M.

    Returns:
        Tensor[]: the loss, float64 for float64 input, else float32.

    Raises:
        ValueError: bad shapes, dtypes or devices (naming ``a``, ``b``, ``a_lengths`` or ``b_lengths``); an empty
            batch or a cloud with no points (N = 0 or M = 0; with the value checks on, a length of 0 or beyond
            N or M); with the value checks on, NaN, infinite or too large coordinates (see :func:`lidarops.knn`).
    """
    check_cloud(a, "a")
    check_cloud(b, "b", batch=a.shape[0])
    check_same_device([("a", a), ("b", b)])
    if a.dtype != b.dtype:
        raise ValueError(f"a and b must have the same dtype, got a {describe(a)} and b {describe(b)}")
    B, N, M = a.shape[0], a.shape[1], b.shape[1]
    if B == 0:
        raise ValueError(f"a must hold at least one cloud (the loss is a mean over the batch), got {describe(a)}")
    for name, t, n in (("a", a, N), ("b", b, M)):
        if n == 0:
            raise ValueError(f"{name} must hold at least one point per cloud (a Chamfer distance to nothing is "
                             f"undefined), got {describe(t)}")
    la = lengths_or_full(a_lengths, a, "a_lengths")
    lb = lengths_or_full(b_lengths, b, "b_lengths")
    if value_checks_enabled():
        ranged = [(la, 1, N, lambda: f"a_lengths must lie in [1, {N}], got {la.tolist()}")] if a_lengths is not None \
            else []
        if b_lengths is not None:
            ranged.append((lb, 1, M, lambda: f"b_lengths must lie in [1, {M}], got {lb.tolist()}"))
        check_values(coords=[(a, "a"), (b, "b")], ranged=ranged)
    with validation(False):  # checked above, under the names of this function's arguments
        d_ab, _ = knn(a, b, 1, la, lb)  # (B, N, 1): each a_i to its nearest b_j
        d_ba, _ = knn(b, a, 1, lb, la)  # (B, M, 1)
    real_a = torch.arange(N, device=a.device)[None, :] < la[:, None]
    real_b = torch.arange(M, device=a.device)[None, :] < lb[:, None]
    zero = d_ab.new_zeros(())
    term_a = torch.where(real_a, d_ab[..., 0], zero).sum(1) / la.to(d_ab.dtype)
    term_b = torch.where(real_b, d_ba[..., 0], zero).sum(1) / lb.to(d_ba.dtype)
    return (term_a + term_b).mean()


def _cosine_matrix(weights: Tensor) -> Tensor:
    """cos_ij = <S_i, S_j> / (|S_i| |S_j| + 1e-10), (B, m, m)."""
    inner = torch.bmm(weights, weights.transpose(1, 2))
    norm = weights.square().sum(dim=-1, keepdim=True).sqrt()
    return inner / (norm * norm.transpose(1, 2) + COSINE_EPS)


def selection_cosine_loss(weights: Tensor, form: str = "paper") -> Tensor:
    """How much the m rows of CAS-Net's soft selection matrix overlap (0 when they pick disjoint points).

    Args:
        weights (Tensor[B, m, N]): the soft selection matrix S~ (each row a softmax over the N points), floating.
        form (str): ``"paper"``: ``sum_{i != j} |cos(S_i, S_j)| / (m (m - 1))``, the mean over ordered pairs of
            rows, in [0, 1]; ``"frobenius"``: the reference code's ``sqrt(sum_{i != j} cos(S_i, S_j)^2)``,
            not normalised. Either is averaged over the batch; 0 when m = 1 (no pairs). See the module docstring
            for where each comes from.

    Returns:
        Tensor[]: the loss in the weights' dtype. The Frobenius form's gradient at exactly 0 (all rows
        orthogonal) is taken as 0.

    Raises:
        ValueError: ``weights`` not a floating (B, m, N) tensor with B, m, N >= 1; ``form`` not one of
            :data:`COSINE_FORMS`.
    """
    check_tensor(weights, "weights")
    if weights.dim() != 3:
        raise ValueError(f"weights must be the (B, m, N) soft selection matrix, got {describe(weights)}")
    if not weights.is_floating_point():
        raise ValueError(f"weights must be floating point, got {describe(weights)}")
    if 0 in weights.shape:
        raise ValueError(f"weights must have B, m, N >= 1 (the loss is a mean over the batch), got {describe(weights)}")
    if not isinstance(form, str) or form not in COSINE_FORMS:
        raise ValueError(f"form must be one of {list(COSINE_FORMS)}, got {form!r}")
    B, m, _ = weights.shape
    if m == 1:
        return (weights * 0).sum() / B  # no pair of rows; keeps the graph
    cos = _cosine_matrix(weights)
    off = cos * (1 - torch.eye(m, dtype=cos.dtype, device=cos.device))
    if form == "paper":
        per_cloud = off.abs().sum(dim=(1, 2)) / (m * (m - 1))
    else:
        per_cloud = torch.linalg.vector_norm(off, dim=(1, 2))
    return per_cloud.mean()


# ---- pure-PyTorch references, used by the tests ----

def _chamfer_reference(a: Tensor, b: Tensor, a_lengths=None, b_lengths=None) -> Tensor:
    """All pairwise squared distances in the input dtype (differentiable), cloud by cloud."""
    total = []
    for c in range(a.shape[0]):
        na = a.shape[1] if a_lengths is None else int(a_lengths[c])
        nb = b.shape[1] if b_lengths is None else int(b_lengths[c])
        d = ((a[c, :na, None, :] - b[c, None, :nb, :]) ** 2).sum(-1)  # (na, nb)
        total.append(d.min(dim=1).values.mean() + d.min(dim=0).values.mean())
    return torch.stack(total).mean()


def _selection_cosine_reference(weights: Tensor, form: str = "paper") -> Tensor:
    """The two loops of the definition, pair by pair."""
    B, m, _ = weights.shape
    losses = []
    for c in range(B):
        s = weights[c]
        terms = []
        for i in range(m):
            for j in range(m):
                if i != j:
                    terms.append((s[i] @ s[j]) / (s[i].norm() * s[j].norm() + COSINE_EPS))
        if not terms:
            losses.append(s.sum() * 0)
        elif form == "paper":
            losses.append(torch.stack(terms).abs().sum() / (m * (m - 1)))
        else:
            losses.append(torch.stack(terms).square().sum().sqrt())
    return torch.stack(losses).mean()
