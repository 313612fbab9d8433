"""PCT's offset-attention layer (Guo et al. 2021, ``SA_Layer`` of PCT's code), as CAS-Net stacks it, with a path
for whole clouds that never holds an N x N matrix.

The layer, for features ``x (B, C, N)``::

    Q = K = W_qk x                       one shared 1x1 projection C -> d, no bias (PCT: q_conv.weight = k_conv.weight)
    V     = W_v x + b_v                  1x1 conv C -> C
    E     = Q^T K                        (B, N, N), no 1/sqrt(d) scale (PCT's offset attention has none)
    P     = softmax(E, dim=-1)           over the keys j of each query i
    A     = P / (1e-9 + P.sum(dim=1))    column re-normalisation: each column j sums to ~1 over the queries i
    x_r   = V A                          x_r[:, j] = sum_i V[:, i] A[i, j]
    out   = x + ReLU(BN(Conv1x1(x - x_r)))

Three paths compute ``x_r`` (:func:`column_normalized_attention`):

* **plain** (``chunk=None``): the formula above with ``torch.bmm``; autograd keeps the N x N matrices.
* **chunked** (``chunk=r`` rows, or ``"auto"``): ``A``'s normalisation divides column j by a number, so
  ``x_r[:, j] = (sum_i V[:, i] P[i, j]) / (1e-9 + sum_i P[i, j])``: one pass over blocks of r query rows
  accumulates the numerator ``V P`` and the column sums ``1^T P`` together (V with a row of ones appended), each
  block's softmax complete because a block holds whole rows. The backward (a ``torch.autograd.Function``)
  recomputes each block from the saved row maxima and sums; its gradients, with ``H = G / D`` (G the gradient
  of ``x_r``, D the column denominators) and ``g_D = -sum_c H x_r``:

      dV = H P^T,    dP = V^T H + 1 g_D^T,    dE = P * (dP - rowsum(P * dP)),    dQ = K dE^T,    dK = Q dE

  (Q and K are one tensor here; autograd adds the two). Same result as the plain path up to rounding.
* **fused** (``chunk="fused"``): the row log-sum-exps of ``E`` (in blocks; on CUDA without a gradient, the ones
  torch's memory-efficient attention kernel returns), then ``x_r`` as one call of torch's
  ``scaled_dot_product_attention`` with the roles of rows and columns swapped (``_attention_fused`` states the
  algebra); its flash and memory-efficient kernels hold no N x N matrix, forward or backward.

Padding (``mask (B, N)``, True = a real point): padded points neither attend nor are attended. A padded key
column j gets ``P[i, j] = 0`` (left out of every softmax over j); a padded query row i gets ``P[i, :] = 0``
(left out of every column sum and of every ``x_r``); BatchNorm's statistics (training) are taken over the real
points only; and the output at a padded point is its input ``x`` unchanged (identity, so stacked layers carry
padding through untouched). The real points' outputs are then exactly those of the layer run on the real points
alone (:func:`_offset_attention_reference` states it that way), whatever the padded features hold.

Memory of the attention, per layer (s = bytes per element of the computation dtype, float32 for float16/bfloat16
inputs in the chunked path; C channels, d qk channels, r rows per block):

* plain, inference: peak ``2 B N^2 s`` (the energies, then the softmax and its re-normalised copy); training:
  ``2 B N^2 s`` kept from forward to backward (P saved by the softmax and the division, A by bmm; ``3 B N^2 s``
  with a mask: the masked copy of P too) and a peak of about ``6 B N^2 s`` while the backward runs.
* chunked, forward: ``B r N s`` (one block, energies turned into probabilities in place) + ``B N (2C + 5) s`` (the
  numerator with its row of column sums, V with its row of ones, row maxima and sums, denominators); kept for the
  backward: ``B N (C + 4) s`` (x_r with the column-sum row, row maxima and sums, denominators) besides Q, K, V;
  backward: ``2 B r N s`` (the block's P and its dP -> dE, in place) + about ``B N (4C + 2d + 4) s`` (H, [H; g_D],
  V with ones, dV, dQ, dK). Nothing of size N x N, forward or backward.

Measured on CPU (every allocation counted after each op; the whole layer, C = 64, d = 16, B = 1, float32,
N = 1024..4096): plain inference ``2.0-2.2 B N^2 s``, plain training step ``6.0-6.1 B N^2 s``; chunked inference
``B r N s + 3.3 B N C s``, chunked training step ``2 B r N s + 9.9 B N C s`` (the layer's convolutions, offsets
and BatchNorm included). At N = 20,000 that is about 9.6 GB against 0.18 GB (r = 832) for one layer's training
step; at N = 65,536, 103 GB against 0.3 GB (r = 256).

``"auto"`` picks the plain path when ``B N^2 <= AUTO_ENTRIES`` (2^24 entries: 64 MiB in float32) and otherwise
chunks of ``r = AUTO_ENTRIES // (B N)`` rows (a multiple of 64 when at least 64), so a block holds at most
``AUTO_ENTRIES`` entries; except on CUDA without a gradient (inference), where large inputs take the fused path:
same result up to the kernels' float32 rounding (a few 1e-4 where the plain path is exact to 1e-6), several
times faster (one layer on 20,000 points: the blocks read and write every energy several times over).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable
from torch.nn import functional as F

from lidarops._checks import positive_int
from lidarops.models import folded
from lidarops.ops.validation import check_tensor, describe

__all__ = ["OffsetAttention", "column_normalized_attention", "AUTO_ENTRIES"]

#: Most entries of one block of energies the ``"auto"`` chunking allows (and the largest B N^2 it runs plain).
AUTO_ENTRIES = 2**24
#: PCT's constant in the column re-normalisation ``A / (1e-9 + A.sum(dim=1))``.
COLUMN_EPS = 1e-9


# ---------------------------------------------------------------------------------------------------------------
# argument checks
# ---------------------------------------------------------------------------------------------------------------
def _check_mask(mask, B: int, N: int, like: Tensor) -> None:
    if mask is None:
        return
    check_tensor(mask, "mask")
    if mask.dtype != torch.bool:
        raise ValueError(f"mask must be a bool tensor (True = a real point), got {describe(mask)}")
    if tuple(mask.shape) != (B, N):
        raise ValueError(f"mask must be (B, N) = ({B}, {N}), got {describe(mask)}")
    if mask.device != like.device:
        raise ValueError(f"mask is on {mask.device} but the features are on {like.device}; move them to one device")


_CHUNK_HELP = "None (plain path), 'auto', 'fused' or an int >= 1 (rows per block)"


def _check_chunk(chunk) -> "int | str | None":
    if chunk is None or (isinstance(chunk, str) and chunk in ("auto", "fused")):
        return chunk
    if isinstance(chunk, str):
        raise ValueError(f"chunk must be {_CHUNK_HELP}, got {chunk!r}")
    try:
        return positive_int(chunk, "chunk")
    except ValueError:
        raise ValueError(f"chunk must be {_CHUNK_HELP}, got {chunk!r}") from None


def _rows_per_chunk(chunk, B: int, N: int) -> "int | None":
    """The rows per block the chunked path runs with; None for the plain path."""
    if chunk is None:
        return None
    if chunk == "auto":
        if B * N * N <= AUTO_ENTRIES:
            return None
        rows = max(1, AUTO_ENTRIES // max(1, B * N))
        return rows - rows % 64 if rows >= 64 else rows
    return chunk


def _check_qkv(q, k, v) -> None:
    for name, t in (("q", q), ("k", k), ("v", v)):
        check_tensor(t, name)
        if t.dim() != 3:
            raise ValueError(f"{name} must be (B, channels, N), got {describe(t)}")
        if not t.is_floating_point():
            raise ValueError(f"{name} must be floating point, got {describe(t)}")
    if q.shape != k.shape:
        raise ValueError(f"q and k must have one shape (B, d, N), got q {describe(q)} and k {describe(k)}")
    if v.shape[0] != q.shape[0] or v.shape[2] != q.shape[2]:
        raise ValueError(f"v must be (B, C, N) with B, N = {q.shape[0]}, {q.shape[2]} (those of q), got {describe(v)}")
    for name, t in (("k", k), ("v", v)):
        if t.dtype != q.dtype:
            raise ValueError(f"{name} must have q's dtype {q.dtype}, got {describe(t)}")
        if t.device != q.device:
            raise ValueError(f"{name} is on {t.device} but q is on {q.device}; move them to one device")


# ---------------------------------------------------------------------------------------------------------------
# the plain path
# ---------------------------------------------------------------------------------------------------------------
def _attention_plain(q: Tensor, k: Tensor, v: Tensor, mask: "Tensor | None") -> Tensor:
    attention = torch.bmm(q.transpose(1, 2), k)  # the energies (B, N, N)
    if mask is not None:  # padded keys out of every softmax; padded query rows made finite, then zeroed
        attention = attention.masked_fill(~mask[:, None, :], -math.inf).masked_fill(~mask[:, :, None], 0.0)
    attention = torch.softmax(attention, dim=-1)
    if mask is not None:
        attention = attention.masked_fill(~mask[:, :, None], 0.0)
    attention = attention / (COLUMN_EPS + attention.sum(dim=1, keepdim=True))
    return torch.bmm(v, attention)


# ---------------------------------------------------------------------------------------------------------------
# the chunked path
# ---------------------------------------------------------------------------------------------------------------
def _block_probabilities(q_rows: Tensor, k: Tensor, mask: "Tensor | None", rows: slice,
                         row_max: "Tensor | None" = None, row_sum: "Tensor | None" = None):
    """P of the query rows ``rows``: (B, r, N), computed in place in one buffer. Without ``row_max``/``row_sum``
    it computes them (forward) and returns them too; with them (backward) it recomputes the same P bit for bit."""
    p = torch.bmm(q_rows.transpose(1, 2), k)
    if mask is not None:
        p.masked_fill_(~mask[:, None, :], -math.inf)
        p.masked_fill_(~mask[:, rows, None], 0.0)
    if row_max is None:
        m = p.amax(dim=-1, keepdim=True)
        p.sub_(m).exp_()
        s = p.sum(dim=-1, keepdim=True)
        p.div_(s)
    else:
        m, s = row_max[:, rows, None], row_sum[:, rows, None]
        p.sub_(m).exp_().div_(s)
    if mask is not None:
        p.masked_fill_(~mask[:, rows, None], 0.0)
    return p, m, s


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


class _ChunkedColumnAttention(torch.autograd.Function):
    """x_r = V A over blocks of query rows, forward and backward; see the module's docstring for the algebra."""

    @staticmethod
    def forward(ctx, q: Tensor, k: Tensor, v: Tensor, mask: "Tensor | None", rows: int) -> Tensor:
        out_dtype = v.dtype
        ct = _compute_dtype(q.dtype)
        with torch.autocast(q.device.type, enabled=False):
            q, k, v = q.to(ct), k.to(ct), v.to(ct)
            B, C, N = v.shape
            v1 = torch.cat([v, v.new_ones(B, 1, N)], 1)  # the row of ones accumulates the column sums
            acc = v.new_zeros(B, C + 1, N)
            row_max, row_sum = v.new_empty(B, N), v.new_empty(B, N)
            for start in range(0, N, rows):
                r = slice(start, min(N, start + rows))
                p, m, s = _block_probabilities(q[:, :, r], k, mask, r)
                row_max[:, r], row_sum[:, r] = m.squeeze(-1), s.squeeze(-1)
                acc.baddbmm_(v1[:, :, r], p)
                del p
            denom = acc[:, C].add(COLUMN_EPS)  # (B, N)
            x_r = acc[:, :C].div_(denom[:, None, :])
        ctx.rows = rows
        ctx.out_dtype = out_dtype
        ctx.dtypes = (q.dtype, k.dtype, v.dtype)
        ctx.save_for_backward(q, k, v, mask, row_max, row_sum, denom, x_r)
        return x_r.to(out_dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        q, k, v, mask, row_max, row_sum, denom, x_r = ctx.saved_tensors
        need_q, need_k, need_v = ctx.needs_input_grad[:3]
        B, C, N = v.shape
        with torch.autocast(q.device.type, enabled=False):
            h = grad.to(v.dtype) / denom[:, None, :]  # H = G / D
            if mask is not None:  # padded columns: D = 1e-9 and P = 0 there; keep H finite
                h = h.masked_fill(~mask[:, None, :], 0.0)
            h1 = torch.cat([h, -(h * x_r).sum(dim=1, keepdim=True)], 1)  # [H; g_D], g_D = -sum_c H x_r
            v1 = torch.cat([v, v.new_ones(B, 1, N)], 1) if (need_q or need_k) else None
            dq = torch.zeros_like(q) if need_q else None
            dk = torch.zeros_like(k) if need_k else None
            dv = torch.empty_like(v) if need_v else None
            for start in range(0, N, ctx.rows):
                r = slice(start, min(N, start + ctx.rows))
                p, _, _ = _block_probabilities(q[:, :, r], k, mask, r, row_max, row_sum)
                if need_v:
                    dv[:, :, r] = torch.bmm(h, p.transpose(1, 2))
                if need_q or need_k:
                    de = torch.bmm(v1[:, :, r].transpose(1, 2), h1)  # dP of the block (B, r, N)
                    de.mul_(p)
                    de.addcmul_(p, de.sum(dim=-1, keepdim=True), value=-1.0)  # dE = P * (dP - rowsum(P * dP))
                    if need_q:
                        dq[:, :, r] = torch.bmm(k, de.transpose(1, 2))
                    if need_k:
                        dk.baddbmm_(q[:, :, r], de)
                    del de
                del p
        dq = dq.to(ctx.dtypes[0]) if need_q else None
        dk = dk.to(ctx.dtypes[1]) if need_k else None
        dv = dv.to(ctx.dtypes[2]) if need_v else None
        return dq, dk, dv, None, None


# ---------------------------------------------------------------------------------------------------------------
# the fused path
# ---------------------------------------------------------------------------------------------------------------
class _RowLogSumExp(torch.autograd.Function):
    """``lse_i = log sum_j exp(q_i . k_j)`` over the real keys, in blocks of query rows (0 at padded rows), with
    its gradient by blocks too: ``dq_i = g_i sum_j P_ij k_j``, ``dk_j = sum_i g_i P_ij q_i``."""

    @staticmethod
    def forward(ctx, q: Tensor, k: Tensor, mask: "Tensor | None", rows: int) -> Tensor:
        ct = _compute_dtype(q.dtype)
        with torch.autocast(q.device.type, enabled=False):
            qc, kc = q.to(ct), k.to(ct)
            B, _, N = qc.shape
            lse = qc.new_empty(B, N)
            for start in range(0, N, rows):
                r = slice(start, min(N, start + rows))
                e = torch.bmm(qc[:, :, r].transpose(1, 2), kc)
                if mask is not None:
                    e.masked_fill_(~mask[:, None, :], -math.inf)
                lse[:, r] = torch.logsumexp(e, dim=-1)
                del e
            if mask is not None:
                lse.masked_fill_(~mask, 0.0)
        ctx.rows, ctx.dtypes = rows, (q.dtype, k.dtype)
        ctx.save_for_backward(qc, kc, mask, lse)
        return lse

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        q, k, mask, lse = ctx.saved_tensors
        with torch.autocast(q.device.type, enabled=False):
            g = grad.to(q.dtype)
            if mask is not None:
                g = g.masked_fill(~mask, 0.0)
            dq, dk = torch.empty_like(q), torch.zeros_like(k)
            N = q.shape[2]
            for start in range(0, N, ctx.rows):
                r = slice(start, min(N, start + ctx.rows))
                p = torch.bmm(q[:, :, r].transpose(1, 2), k)
                if mask is not None:
                    p.masked_fill_(~mask[:, None, :], -math.inf)
                p.sub_(lse[:, r, None]).exp_()  # P of the block: exp(e - lse)
                if mask is not None:
                    p.masked_fill_(~mask[:, r, None], 0.0)
                p.mul_(g[:, r, None])  # g_i P_ij
                dq[:, :, r] = torch.bmm(k, p.transpose(1, 2))
                dk.baddbmm_(q[:, :, r], p)
                del p
        return dq.to(ctx.dtypes[0]), dk.to(ctx.dtypes[1]), None, None


def _row_logsumexp_fused(q: Tensor, k: Tensor, mask: "Tensor | None", dt: torch.dtype) -> "Tensor | None":
    """:class:`_RowLogSumExp`'s forward without a gradient, from the log-sum-exps that torch's attention kernels
    return beside their output (:func:`_kernel_logsumexp`; queries ``q_i``, keys ``k_j``, scale 1; padded keys get
    one more coordinate of score ``-max/4``): no block of energies is written out. Float32 result, 0 at padded
    rows; None where the kernels refuse the inputs (the caller then takes the blocks)."""
    B, d, N = q.shape
    if mask is None and k is q and d % 8 == 0:  # PCT's layer: one tensor for q and k, no padding to add
        qt = q.transpose(1, 2).unsqueeze(1).to(dt).contiguous()
        lse = _kernel_logsumexp(qt, qt, qt)
        return None if lse is None else lse[:, :N].float()
    width = -(-(d + (mask is not None)) // 8) * 8
    queries = q.new_zeros(B, 1, N, width, dtype=dt)
    keys = q.new_zeros(B, 1, N, width, dtype=dt)
    queries[:, 0, :, :d] = q.transpose(1, 2).to(dt)
    keys[:, 0, :, :d] = k.transpose(1, 2).to(dt)
    if mask is not None:
        queries[:, 0, :, d] = 1.0
        keys[:, 0, :, :d] = keys[:, 0, :, :d].masked_fill(~mask[:, :, None], 0.0)
        keys[:, 0, :, d] = keys[:, 0, :, d].masked_fill(~mask, -torch.finfo(dt).max / 4)
    lse = _kernel_logsumexp(queries, keys, q.new_zeros(B, 1, N, 8, dtype=dt))
    if lse is None:
        return None
    lse = lse[:, :N].float()
    return lse if mask is None else lse.masked_fill(~mask, 0.0)


def _kernel_logsumexp(queries: Tensor, keys: Tensor, values: Tensor) -> "Tensor | None":
    """The row log-sum-exps ``(B, >= N)`` of ``queries . keys`` (scale 1; ``(B, 1, N, d)`` each) that torch's
    attention kernels return beside their output: cuDNN's in half precision (the faster), else the
    memory-efficient kernel's; None where neither takes the inputs."""
    B = queries.shape[0]
    if queries.dtype in (torch.float16, torch.bfloat16):
        try:
            lse = torch.ops.aten._scaled_dot_product_cudnn_attention(queries, keys, values, None, True, 0.0, False,
                                                                     False, scale=1.0)[1]
            return lse.reshape(B, -1)
        except (RuntimeError, NotImplementedError):
            pass
    try:
        lse = torch.ops.aten._scaled_dot_product_efficient_attention(queries, keys, values, None, True, 0.0, False,
                                                                      scale=1.0)[1]
    except (RuntimeError, NotImplementedError):
        return None
    return lse[:, 0]


def _attention_fused(q: Tensor, k: Tensor, v: Tensor, mask: "Tensor | None", rows: int) -> Tensor:
    """``x_r`` by one call of torch's fused attention (``scaled_dot_product_attention``), which never holds the
    N x N matrix (flash or memory-efficient kernels on CUDA, blocked kernels on the CPU).

    With the row log-sum-exps ``lse_i`` of ``E = Q^T K`` (:class:`_RowLogSumExp`), ``P_ij = exp(e_ij - lse_i)``,
    and ``x_r[:, j] = sum_i V_i P_ij / (1e-9 + sum_i P_ij)`` is an attention of query j over keys i with scores
    ``s_ji = k_j . q_i - lse_i``, normalised over i: the keys ``[q_i, -lse_i]`` meet the queries ``[k_j, 1]``
    (``lse`` split into a float16-exact high part and the rest, two coordinates, so that half precision keeps it),
    and one more key of score ``log(1e-9)`` and value 0 adds PCT's 1e-9 to every denominator. Padded rows i are
    keys of score -inf (the extra key keeps every softmax finite); padded columns j are set to 0."""
    B, d, N = q.shape
    C = v.shape[1]
    dt = q.dtype if not torch.is_autocast_enabled(q.device.type) else torch.get_autocast_dtype(q.device.type)
    lse = None
    if q.is_cuda and not (torch.is_grad_enabled() and (q.requires_grad or k.requires_grad)):
        lse = _row_logsumexp_fused(q, k, mask, dt)
    if lse is None:
        lse = _RowLogSumExp.apply(q, k, mask, rows)
    # float16's rounding of lse (exact in every dtype the kernels take) and the rest, which carries the gradient
    # (through a float16 cast the gradient would be rounded too)
    half = torch.finfo(torch.float16).max
    hi = lse.detach().clamp(-half, half).to(torch.float16).to(lse.dtype)
    lo = lse - hi
    width = -(-max(d + 2, C) // 8) * 8  # the fused kernels want one head size for all three, a multiple of 8
    queries = q.new_zeros(B, N, width, dtype=dt)
    queries[:, :, :d] = k.transpose(1, 2).to(dt)
    queries[:, :, d:d + 2] = 1.0
    keys = q.new_zeros(B, N + 1, width, dtype=dt)
    keys[:, :N, :d] = q.transpose(1, 2).to(dt)
    keys[:, :N, d] = -hi.to(dt)
    keys[:, :N, d + 1] = -lo.to(dt)
    keys[:, N, d] = math.log(COLUMN_EPS)
    if mask is not None:  # padded rows i: keys that no query reaches; padded columns j: zero queries (finite)
        keys[:, :N] = keys[:, :N].masked_fill(~mask[:, :, None], 0.0)
        keys[:, :N, d] = keys[:, :N, d].masked_fill(~mask, -torch.finfo(dt).max / 4)
        queries = queries.masked_fill(~mask[:, :, None], 0.0)
    values = v.new_zeros(B, N + 1, width, dtype=dt)  # flash kernels want the values' size too
    values[:, :N, :C] = v.transpose(1, 2).to(dt)
    out = F.scaled_dot_product_attention(queries[:, None], keys[:, None], values[:, None], scale=1.0)[:, 0, :, :C]
    x_r = out.transpose(1, 2).to(v.dtype if not torch.is_autocast_enabled(q.device.type) else out.dtype)
    if mask is not None:
        x_r = x_r.masked_fill(~mask[:, None, :], 0.0)
    return x_r


def column_normalized_attention(q: Tensor, k: Tensor, v: Tensor, mask: "Tensor | None" = None,
                                chunk: "int | str | None" = None) -> Tensor:
    """``x_r = V A`` of offset attention: ``A = P / (1e-9 + P.sum(dim=1))``, ``P = softmax(Q^T K, dim=-1)``.

    Args:
        q (Tensor[B, d, N]), k (Tensor[B, d, N]): queries and keys (one tensor in PCT's layer), floating.
        v (Tensor[B, C, N]): values, same dtype and device.
        mask (Tensor[B, N] bool, optional): True = a real point; padded keys get no weight and padded queries
            take no part in the column sums (their columns of ``x_r`` are 0).
        chunk: ``None`` (plain path, N x N matrices), an int (the chunked path with blocks of that many query
            rows; never an N x N matrix, forward or backward), ``"auto"`` (plain or chunked by size; fused for
            large inputs on CUDA without a gradient; see :data:`AUTO_ENTRIES`) or
            ``"fused"`` (torch's fused attention kernels; never an N x N matrix either, see :func:`_attention_fused`).

    Returns:
        Tensor[B, C, N]: ``x_r`` in v's dtype (the chunked path computes float16/bfloat16 in float32).

    Raises:
        ValueError: shapes, dtypes or devices that do not fit, a bad ``mask`` or ``chunk``.
    """
    _check_qkv(q, k, v)
    B, _, N = q.shape
    _check_mask(mask, B, N, q)
    chunk = _check_chunk(chunk)
    if B == 0 or N == 0:
        return v * 0  # empty
    rows = _rows_per_chunk(chunk, B, N)
    if chunk == "auto" and rows is not None and q.is_cuda and not (
            torch.is_grad_enabled() and (q.requires_grad or k.requires_grad or v.requires_grad)):
        chunk = "fused"  # inference on CUDA: no block of energies written out at all
    if chunk == "fused":
        return _attention_fused(q, k, v, mask, _rows_per_chunk("auto", B, N) or N)
    if rows is None:
        return _attention_plain(q, k, v, mask)
    return _ChunkedColumnAttention.apply(q, k, v, mask, rows)


# ---------------------------------------------------------------------------------------------------------------
# the layer
# ---------------------------------------------------------------------------------------------------------------
class OffsetAttention(nn.Module):
    """PCT's offset-attention layer (``SA_Layer``; CAS-Net's OA), with its parameter names (``q_conv``,
    ``k_conv``, ``v_conv``, ``trans_conv``, ``after_norm``) so PCT and CAS-Net checkpoints load.

    Args:
        channels (int): C, the feature channels in and out.
        qk_channels (int): d, the shared query/key projection's channels (PCT: C / 4).
        chunk: the default path of :meth:`forward`: ``None`` (plain), an int (rows per block of the chunked path),
            ``"auto"`` (plain for small inputs, chunked for large ones, fused for large ones on CUDA without a
            gradient; see :data:`AUTO_ENTRIES`) or ``"fused"``
            (torch's fused attention, :func:`column_normalized_attention`).

    Shapes: ``x (B, C, N)`` -> ``(B, C, N)``; ``mask (B, N)`` bool, True = a real point (see the module docstring:
    padded points neither attend nor are attended, BatchNorm's statistics skip them, their output is ``x``).
    """

    def __init__(self, channels: int = 64, qk_channels: int = 16, chunk: "int | str | None" = "auto"):
        super().__init__()
        channels, qk_channels = positive_int(channels, "channels"), positive_int(qk_channels, "qk_channels")
        self.channels, self.qk_channels = channels, qk_channels
        self.chunk = _check_chunk(chunk)
        self.q_conv = nn.Conv1d(channels, qk_channels, 1, bias=False)
        self.k_conv = nn.Conv1d(channels, qk_channels, 1, bias=False)
        self.k_conv.weight = self.q_conv.weight  # one projection for Q and K, as PCT
        self.v_conv = nn.Conv1d(channels, channels, 1)
        self.trans_conv = nn.Conv1d(channels, channels, 1)
        self.after_norm = nn.BatchNorm1d(channels)
        self.act = nn.ReLU()

    def extra_repr(self) -> str:
        return f"channels={self.channels}, qk_channels={self.qk_channels}, chunk={self.chunk!r}"

    def forward(self, x: Tensor, mask: "Tensor | None" = None, chunk: "int | str | None" = ...) -> Tensor:
        """Args:
            x (Tensor[B, C, N]): features, floating, on the layer's device.
            mask (Tensor[B, N] bool, optional): True = a real point.
            chunk: overrides the layer's ``chunk`` for this call (``...``, the default, keeps it).

        Returns:
            Tensor[B, C, N]: ``x + ReLU(BN(trans_conv(x - x_r)))`` at real points, ``x`` at padded ones.
        """
        check_tensor(x, "x")
        if x.dim() != 3 or x.shape[1] != self.channels:
            raise ValueError(f"x must be (B, C, N) with C = {self.channels}, got {describe(x)}")
        if not x.is_floating_point():
            raise ValueError(f"x must be floating point, got {describe(x)}")
        weight = self.q_conv.weight
        if x.device != weight.device:
            raise ValueError(f"x is on {x.device} but the layer is on {weight.device}; move them to one device")
        if x.dtype != weight.dtype and not torch.is_autocast_enabled(x.device.type):
            raise ValueError(f"x must have the layer's dtype {weight.dtype} (or run under torch.autocast), "
                             f"got {describe(x)}")
        B, _, N = x.shape
        _check_mask(mask, B, N, x)
        chunk = self.chunk if chunk is ... else _check_chunk(chunk)
        if B == 0 or N == 0:
            return x.clone()
        q = self.q_conv(x)
        k = q if self.k_conv.weight is self.q_conv.weight else self.k_conv(x)
        x_r = column_normalized_attention(q, k, self.v_conv(x), mask, chunk)
        y = self.trans_conv(x - x_r)
        if mask is None:
            return x + self.act(self.after_norm(y))
        # BatchNorm over the real points only (its statistics and running averages), padded points unchanged
        yt = y.transpose(1, 2)
        real = yt[mask]  # (P, C)
        if real.shape[0] == 0:  # only padding: nothing to normalise
            return x.clone()
        delta = torch.zeros_like(yt).index_put((mask,), self.act(self.after_norm(real)))
        return x + delta.transpose(1, 2)

    def rows(self, x: Tensor) -> Tensor:
        """:meth:`forward` in eval mode without padding, on rows: ``x (B, N, C)`` -> ``(B, N, C)``, the
        convolutions as ``F.linear`` with BatchNorm folded into ``trans_conv`` (:mod:`lidarops.models.folded`)."""
        if self.training:
            return self(x.transpose(1, 2)).transpose(1, 2)
        shared = self.k_conv.weight is self.q_conv.weight
        wq, wk, wv, bv, wt, bt = folded.cached(self, "rows", folded.compute_dtype(x), lambda: (
            self.q_conv.weight[:, :, 0], self.k_conv.weight[:, :, 0], *folded.conv_bn(self.v_conv),
            *folded.conv_bn(self.trans_conv, self.after_norm)))
        q = F.linear(x, wq).transpose(1, 2)  # (B, d, N) views of rows: what the fused kernels take
        k = q if shared else F.linear(x, wk).transpose(1, 2)
        x_r = column_normalized_attention(q, k, F.linear(x, wv, bv).transpose(1, 2), None, self.chunk).transpose(1, 2)
        return x + F.relu(F.linear(x - x_r, wt, bt), inplace=True)


# ---------------------------------------------------------------------------------------------------------------
# the reference
# ---------------------------------------------------------------------------------------------------------------
def _offset_attention_reference(x: Tensor, q_weight: Tensor, v_weight: Tensor, v_bias: Tensor, trans_weight: Tensor,
                                trans_bias: Tensor, bn_weight: Tensor, bn_bias: Tensor, running_mean: Tensor,
                                running_var: Tensor, training: bool, momentum: float = 0.1, bn_eps: float = 1e-5,
                                mask: "Tensor | None" = None) -> Tensor:
    """PCT's ``SA_Layer.forward`` written out literally, cloud by cloud on the real points only (padded points
    do not exist for it; their output is their input). BatchNorm pools the real points of every cloud, as one
    ``F.batch_norm`` call; in training it updates ``running_mean``/``running_var`` in place, as the layer does.

    Args: the layer's weights as tensors (``q_weight (d, C, 1)``, ``v_weight (C, C, 1)``, ``v_bias (C,)``,
    ``trans_weight (C, C, 1)``, ``trans_bias (C,)``) and its BatchNorm's parameters and buffers.
    """
    B, C, N = x.shape
    mask = torch.ones(B, N, dtype=torch.bool, device=x.device) if mask is None else mask
    offsets = []
    for b in range(B):
        xb = x[b:b + 1, :, mask[b]]  # (1, C, n): the real points of cloud b
        if xb.shape[2] == 0:
            continue
        x_q = F.conv1d(xb, q_weight).permute(0, 2, 1)  # (1, n, d)
        x_k = F.conv1d(xb, q_weight)  # (1, d, n): the same weight
        x_v = F.conv1d(xb, v_weight, v_bias)  # (1, C, n)
        energy = torch.bmm(x_q, x_k)  # (1, n, n)
        attention = torch.softmax(energy, dim=-1)
        attention = attention / (1e-9 + attention.sum(dim=1, keepdim=True))
        x_r = torch.bmm(x_v, attention)  # (1, C, n)
        offsets.append(xb - x_r)
    if not offsets:  # only padding
        return x.clone()
    y = F.conv1d(torch.cat(offsets, dim=2), trans_weight, trans_bias)  # (1, C, P): every real point of the batch
    y = F.batch_norm(y, running_mean, running_var, bn_weight, bn_bias, training, momentum, bn_eps)
    out = x.clone()
    out.permute(0, 2, 1)[mask] = (x.permute(0, 2, 1)[mask] + F.relu(y[0].t()))
    return out
