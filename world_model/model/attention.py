"""Attention layers of the DiT and the masks they use.

Linear layers are named plainly (``q``, ``k``, ``v``, ``o``) so LoRA (peft ``target_modules``)
finds them. All attention goes through :func:`attention`; boolean masks are True where attention is allowed
(:func:`mask_bias` turns one into the additive bias the DiT passes).

KV hook for the causal student: :meth:`SelfAttention.forward` returns the (RoPE-rotated) keys
and values it computed, and accepts extra context keys/values that are prepended to its own.
A streaming engine can thus keep an explicit per-layer cache of past frames.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from world_model.model.rope import apply_rope

KV = tuple[torch.Tensor, torch.Tensor]  # keys, values: (N, heads, S, head_dim)


def block_causal_mask(
    frames: int,
    tokens_per_frame: int,
    chunk_frames: int,
    context_frames: int = 0,
    device: torch.device | str = "cpu",
    blocks: torch.Tensor | None = None,
) -> torch.Tensor:
    """(S, Sc + S) bool for S = frames * tokens_per_frame queries and Sc context tokens.

    Query frame f (chunk ``f // chunk_frames``) sees every context frame and the frames of its
    own and earlier chunks: a chunk's output never depends on later chunks. ``blocks`` (frames,)
    non-decreasing ints, when given, replaces the regular chunking (e.g. a rollout whose first
    block is a single conditioning frame).
    """
    chunk = torch.arange(frames, device=device) // chunk_frames if blocks is None else blocks.to(device)
    allowed = chunk[:, None] >= chunk[None, :]  # (T, T)
    allowed = torch.cat([torch.ones(frames, context_frames, dtype=torch.bool, device=device), allowed], dim=1)
    return allowed.repeat_interleave(tokens_per_frame, 0).repeat_interleave(tokens_per_frame, 1)


def cross_view_mask(adjacency: torch.Tensor, tokens_per_view: int) -> torch.Tensor:
    """(B, V, V) view adjacency -> (B, V*n, V*n) token mask for views laid out view-major."""
    return adjacency.repeat_interleave(tokens_per_view, 1).repeat_interleave(tokens_per_view, 2)


def mask_bias(mask: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor | None:
    """Bool mask (True = attend) -> additive bias of ``dtype``: 0 where allowed, the dtype's lowest
    value where not (not -inf: a fully masked row then averages its values instead of turning into
    NaN). Build it once per forward: on CPU inductor fuses an addition into the softmax better than
    a boolean ``masked_fill`` (m4world bench model measures the whole forward)."""
    if mask is None:
        return None
    return torch.zeros(mask.shape, dtype=dtype, device=mask.device).masked_fill_(~mask, torch.finfo(dtype).min)


def attention(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None = None, scale: float | None = None
) -> torch.Tensor:
    """Softmax attention: q (..., S, d), k/v (..., Sk, d), ``mask`` broadcastable to (..., S, Sk):
    bool (True = attend) or an additive bias from :func:`mask_bias`. ``scale`` multiplies the
    scores (default ``d ** -0.5``; 1 when the queries or keys already carry it).

    On CPU two batched matmuls and a softmax: at the DiT's short sequences (tens to a few hundred
    tokens) that is about twice as fast as ``scaled_dot_product_attention``'s CPU flash kernel
    (m4world bench model). Masked scores get the dtype's lowest value rather than -inf, so
    a fully masked row averages its values instead of turning into NaN. Elsewhere SDPA's fused
    kernels win.
    """
    scale = q.shape[-1] ** -0.5 if scale is None else scale
    if q.device.type != "cpu":
        return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=scale)
    if scale != 1.0:
        q = q * scale  # scale the smaller operand
    scores = torch.matmul(q, k.transpose(-1, -2))
    if mask is not None:
        if mask.dtype == torch.bool:
            scores = scores.masked_fill(~mask, torch.finfo(scores.dtype).min)
        else:
            scores = scores + mask.to(scores.dtype)
    return torch.matmul(torch.softmax(scores, dim=-1), v)


class RMSNorm(nn.Module):
    """The QK-norm's parameters: ``x / rms(x) * weight`` over the last dim, mean square in float32.

    It has no ``forward``: the attention layers multiply by :meth:`inverse_rms` and fold ``weight``
    into the next factor of the dot product (the rotary tables, or the keys of a cross-attention),
    which saves several passes over the queries and keys per layer; in bf16 on CPU the whole norm
    cost more than the attention matmuls (m4world bench student)."""

    def __init__(self, dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def inverse_rms(self, x: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., 1) ``1 / sqrt(mean(x^2) + eps)`` in x's dtype (reduced in float32)."""
        norm = torch.linalg.vector_norm(x, dim=-1, keepdim=True, dtype=torch.float32)
        return torch.rsqrt(norm.square() / x.shape[-1] + self.eps).to(x.dtype)


def _normed_rotated(
    x: torch.Tensor, heads: int, norm: RMSNorm, cos: torch.Tensor, sin: torch.Tensor, gain: float
) -> torch.Tensor:
    """(N, S, D) -> (N, H, S, hd): each head RMS-normalized by ``norm``, times ``gain``, rotated.

    The norm's weight (and ``gain``) is folded into the rotary tables: RoPE turns the pair
    (i, i + hd/2) by one angle, so rotating ``w * x`` is ``(cos * w) x + (sin * swap(w)) swap(x)``,
    and the per-token ``1/rms`` commutes with the rotation."""
    x = x.unflatten(-1, (heads, -1))  # (N, S, H, hd)
    w = norm.weight.float() * gain
    half = w.shape[0] // 2
    cos_w = (cos.float() * w).to(x.dtype)
    sin_w = (sin.float() * torch.cat([w[half:], w[:half]])).to(x.dtype)
    return apply_rope((x * norm.inverse_rms(x)).transpose(-3, -2), cos_w, sin_w)


def _heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(..., S, D) -> (..., H, S, D/H)."""
    return x.unflatten(-1, (heads, -1)).transpose(-3, -2)


def _merge(x: torch.Tensor) -> torch.Tensor:
    """(..., H, S, d) -> (..., S, H*d)."""
    return x.transpose(-3, -2).flatten(-2)


class SelfAttention(nn.Module):
    """Multi-head self-attention with QK-norm (RMSNorm per head) and rotary positions."""

    def __init__(self, dim: int, heads: int, eps: float) -> None:
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.o = nn.Linear(dim, dim)
        self.q_norm = RMSNorm(dim // heads, eps)
        self.k_norm = RMSNorm(dim // heads, eps)

    def forward(
        self,
        x: torch.Tensor,
        cos: torch.Tensor,
        sin: torch.Tensor,
        mask: torch.Tensor | None = None,
        context: KV | None = None,
        queries_from: int = 0,
    ) -> tuple[torch.Tensor, KV]:
        """x (N, S, D); cos/sin (S, head_dim) from ``rope.rotation_tables``; mask (S, Sc+S) or
        (N, 1, S, Sc+S) or None (full); context keys/values (N, H, Sc, head_dim). Returns output
        (N, S - queries_from, D) of the tokens from ``queries_from`` on (the others only give keys
        and values) and this call's own (k, v) (N, H, S, head_dim), rotated, ready to be cached."""
        xq = x[:, queries_from:] if queries_from else x
        # The softmax scale rides on the queries' rotary tables.
        scale = cos.shape[-1] ** -0.5
        q = _normed_rotated(self.q(xq), self.heads, self.q_norm, cos[queries_from:], sin[queries_from:], scale)
        if mask is not None and queries_from:
            mask = mask[..., queries_from:, :]
        k = _normed_rotated(self.k(x), self.heads, self.k_norm, cos, sin, 1.0)
        v = _heads(self.v(x), self.heads)
        k_all, v_all = k, v
        if context is not None:
            k_all = torch.cat([context[0].to(k.dtype), k], dim=2)
            v_all = torch.cat([context[1].to(v.dtype), v], dim=2)
        out = attention(q, k_all, v_all, mask, scale=1.0)
        return self.o(_merge(out)), (k, v)


class CrossAttention(nn.Module):
    """Queries from the video tokens, keys/values from a context of width ``ctx_dim``."""

    def __init__(self, dim: int, ctx_dim: int, heads: int, eps: float) -> None:
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(ctx_dim, dim)
        self.v = nn.Linear(ctx_dim, dim)
        self.o = nn.Linear(dim, dim)
        self.q_norm = RMSNorm(dim // heads, eps)
        self.k_norm = RMSNorm(dim // heads, eps)

    def kv(self, ctx: torch.Tensor) -> KV:
        """ctx (..., Sc, ctx_dim) -> keys, values (..., H, Sc, head_dim). The keys also carry the
        query norm's weight and the softmax scale (``sum_d q_d w_d k_d`` is the same with ``w`` on
        either side), so :meth:`attend`, run more often than this, only divides by the rms."""
        k = self.k(ctx).unflatten(-1, (self.heads, -1))
        gain = self.k_norm.weight.float() * self.q_norm.weight.float() * k.shape[-1] ** -0.5
        k = k * self.k_norm.inverse_rms(k) * gain.to(k.dtype)
        return k.transpose(-3, -2), _heads(self.v(ctx), self.heads)

    def attend(self, x: torch.Tensor, kv: KV, mask: torch.Tensor | None) -> torch.Tensor:
        """x (N, S, D), kv from :meth:`kv` (N, H, Sc, hd), mask broadcastable to (N, H, S, Sc) -> (N, S, D)."""
        q = self.q(x).unflatten(-1, (self.heads, -1))
        q = (q * self.q_norm.inverse_rms(q)).transpose(-3, -2)
        k, v = kv
        out = attention(q, k.to(q.dtype), v.to(q.dtype), mask, scale=1.0)
        return self.o(_merge(out))

    def forward(self, x: torch.Tensor, ctx: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return self.attend(x, self.kv(ctx), mask)
