"""Multi-view + LiDAR diffusion transformer (§3.2, Fig. 2).

Latents are ``(B, T, V, C, h, w)`` (frames, views = cameras + LiDAR last). Inside, each view is
its own token sequence of ``T * N`` tokens (N = tokens per frame), and the view axis is folded
into the batch: ``(B*V, T*N, D)``. Every block has

1. spatio-temporal self-attention within a view (3-D RoPE, QK-norm, per-frame adaLN
   modulation from the timestep, bidirectional or block-causal);
2. text cross-attention (the scene prompt, shared by all views and frames);
3. control cross-attention: a token of frame f of view v sees the sensor token of v and the
   ego, map and object tokens of frame f only (controls are per-frame, §3.2);
4. every ``cross_view_every``-th block, cross-view attention: at each frame, the tokens of a view
   attend to the tokens of the views whose fields of view overlap. Only here do views meet, so
   the view axis could be split across devices ("sensor parallelism", §4.4);
5. an MLP (``fc1``/``fc2``), adaLN-modulated and gated.

Hooks: ``forward(..., kv_context=, frame_offset=, return_kv=, context_only_frames=)`` for a causal
streaming engine;
``DitConfig.in_channels_extra`` for reference conditioning (§6). With ``LayoutConfig.enabled`` the
per-view layout raster (:mod:`world_model.model.layout`, from the conditions) enters as input
channels between the latent's and the reference's: ``[latent | layout | reference]``.
"""

from __future__ import annotations

import math
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from world_model.model.attention import (
    KV,
    CrossAttention,
    SelfAttention,
    block_causal_mask,
    cross_view_mask,
    mask_bias,
)
from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig
from world_model.model.rope import rope_tables, rotation_tables
from world_model.model.rows import whole_if_split_free
from world_model.model.tokens import ControlTokenizer, ControlTokens, frame_rows
from world_model.precision import bf16_autocast, built_autocast_bf16

MODULATIONS = 6  # shift, scale, gate for attention and for the MLP


@dataclass(frozen=True)
class _Hooks:
    """The streaming hooks of one :meth:`MultiViewDiT.forward` (its keyword arguments, documented there)."""

    causal: bool
    frame_offset: int
    kv_context: list[KV] | None
    return_kv: bool
    blocks: torch.Tensor | None
    context_valid: torch.Tensor | None
    context_only_frames: int


@dataclass
class _Run:
    """Per-forward state shared by all blocks: B samples of V views, T frames of N tokens each."""

    b: int
    v: int
    t: int
    n: int
    mod: torch.Tensor  # (B, T, 6, D) timestep modulation
    cos: torch.Tensor  # RoPE tables of the T * N tokens (rope.rotation_tables)
    sin: torch.Tensor
    # Attention masks as additive biases (attention.mask_bias) in the blocks' compute dtype.
    self_mask: torch.Tensor | None  # (S, Sc + S) or (B*V, 1, S, Sc + S)
    tokens: ControlTokens
    text_mask: torch.Tensor  # (B, 1, 1, L + 1)
    control_mask: torch.Tensor  # (B*T, 1, V*N, V + Nf)
    view_mask: torch.Tensor  # (B*T, 1, V*N, V*N)

    def frame_rows(self, x: torch.Tensor, first: int) -> torch.Tensor:
        """Rows (B*T, ...) of per-frame tensors -> the rows of frames ``first``.. (B*(T - first), ...)."""
        return frame_rows(x, self.b, self.t, first, self.t)

    def frames_from(self, first: int) -> _Run:
        """The state of frames ``first``.. only: the queries of a block whose earlier frames give
        keys and values but no output (see ``MultiViewDiT.forward``'s ``context_only_frames``)."""
        s = first * self.n
        return replace(
            self,
            t=self.t - first,
            mod=self.mod[:, first:],
            cos=self.cos[s:],
            sin=self.sin[s:],
            self_mask=None,  # the self-attention runs with the full run's mask
            control_mask=self.frame_rows(self.control_mask, first),
            view_mask=self.frame_rows(self.view_mask, first),
        )


def _control_keys(tokens: ControlTokens) -> torch.Tensor:
    """Per frame: keys (B*T, V + Nf, Dc) = the V sensor tokens, then that frame's controls."""
    b, t, nf, dc = tokens.frame.shape
    v = tokens.sensor.shape[1]
    return torch.cat([tokens.sensor[:, None].expand(b, t, v, dc), tokens.frame], dim=2).reshape(b * t, v + nf, dc)


def _control_mask(tokens: ControlTokens, n: int) -> torch.Tensor:
    """(B*T, 1, V*N, V + Nf): a query of view v at frame f sees sensor v and f's valid controls."""
    b, t, nf, _ = tokens.frame.shape
    v = tokens.sensor.shape[1]
    sensor_ok = torch.eye(v, dtype=torch.bool, device=tokens.frame.device).repeat_interleave(n, dim=0)  # (V*N, V)
    frame_ok = tokens.frame_mask.reshape(b * t, 1, 1, nf).expand(b * t, 1, v * n, nf)
    return torch.cat([sensor_ok[None, None].expand(b * t, 1, v * n, v), frame_ok], dim=-1)


def _context_mask(self_mask: torch.Tensor | None, valid: torch.Tensor, t_len: int, n: int, v: int) -> torch.Tensor:
    """Per-sample self-attention mask (B*V, 1, S, Sc + S) from per-frame context validity (B, Fc)."""
    b, fc = valid.shape
    s = t_len * n
    keys = torch.cat([valid.repeat_interleave(n, dim=1), valid.new_ones(b, s)], dim=1)  # (B, Sc + S)
    mask = keys[:, None, :].expand(b, s, fc * n + s)
    if self_mask is not None:
        mask = mask & self_mask
    return mask.repeat_interleave(v, dim=0)[:, None]


def _sincos_2d(dim: int, rows: int, cols: int) -> torch.Tensor:
    """(rows * cols, dim) fixed sin-cos embedding; half the channels for rows, half for columns."""
    quarter = dim // 4
    freqs = 1.0 / 10000.0 ** (torch.arange(quarter, dtype=torch.float64) / quarter)
    r = torch.arange(rows, dtype=torch.float64)[:, None] * freqs
    c = torch.arange(cols, dtype=torch.float64)[:, None] * freqs
    emb = torch.cat(
        [
            torch.cat([r.sin(), r.cos()], dim=1)[:, None].expand(rows, cols, -1),
            torch.cat([c.sin(), c.cos()], dim=1)[None].expand(rows, cols, -1),
        ],
        dim=-1,
    ).reshape(rows * cols, -1)
    return F.pad(emb, (0, dim - emb.shape[1])).float()


class TimestepEmbedding(nn.Module):
    def __init__(self, dim: int, freq_dim: int, scale: float) -> None:
        super().__init__()
        self.freq_dim, self.scale = freq_dim, scale
        self.fc1 = nn.Linear(freq_dim, dim)
        self.fc2 = nn.Linear(dim, dim)

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """t (...) in [0, 1] -> (..., dim)."""
        half = self.freq_dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device) / half)
        ang = (t.float() * self.scale)[..., None] * freqs
        return self.fc2(F.silu(self.fc1(torch.cat([ang.cos(), ang.sin()], dim=-1))))


class DiTBlock(nn.Module):
    def __init__(self, cfg: ModelConfig, cross_view: bool) -> None:
        super().__init__()
        d, h, eps, dc = cfg.dit.dim, cfg.dit.heads, cfg.dit.norm_eps, cfg.control.dim
        self.norm1 = nn.LayerNorm(d, elementwise_affine=False, eps=eps)
        self.attn = SelfAttention(d, h, cfg.dit.qk_norm_eps)
        self.norm_text = nn.LayerNorm(d, eps=eps)
        self.text_attn = CrossAttention(d, dc, h, cfg.dit.qk_norm_eps)
        self.norm_control = nn.LayerNorm(d, eps=eps)
        self.control_attn = CrossAttention(d, dc, h, cfg.dit.qk_norm_eps)
        self.cross_view = None
        if cross_view:
            self.norm_view = nn.LayerNorm(d, eps=eps)
            self.cross_view = CrossAttention(d, d, h, cfg.dit.qk_norm_eps)
            # Starts as identity so inserting it does not disturb the per-view pathway.
            nn.init.zeros_(self.cross_view.o.weight)
            nn.init.zeros_(self.cross_view.o.bias)
        self.norm2 = nn.LayerNorm(d, elementwise_affine=False, eps=eps)
        hidden = int(d * cfg.dit.mlp_ratio)
        self.fc1 = nn.Linear(d, hidden)
        self.fc2 = nn.Linear(hidden, d)
        self.modulation = nn.Parameter(torch.zeros(MODULATIONS, d))

    def _per_frame(self, x: torch.Tensor, run: _Run) -> torch.Tensor:
        return x.view(run.b, run.v, run.t, run.n, x.shape[-1])

    def _frame_major(self, x: torch.Tensor, run: _Run) -> torch.Tensor:
        """(B*V, T*N, D) -> (B*T, V*N, D)."""
        return self._per_frame(x, run).transpose(1, 2).reshape(run.b * run.t, run.v * run.n, -1)

    def _view_major(self, x: torch.Tensor, run: _Run) -> torch.Tensor:
        """(B*T, V*N, D) -> (B*V, T*N, D)."""
        return x.view(run.b, run.t, run.v, run.n, -1).transpose(1, 2).reshape(run.b * run.v, run.t * run.n, -1)

    def cross_kv(self, tokens: ControlTokens) -> tuple[KV, KV]:
        """Keys/values of the text and the control cross-attention: they depend on the controls only."""
        return self.text_attn.kv(tokens.text), self.control_attn.kv(_control_keys(tokens))

    def forward(
        self, x: torch.Tensor, run: _Run, context: KV | None, cross: tuple[KV, KV], out: _Run | None = None
    ) -> tuple[torch.Tensor, KV]:
        """x (B*V, T*N, D) -> (B*V, T'*N, D), plus this block's self-attention (k, v) of all T frames.
        ``cross``: :meth:`cross_kv`. ``out``: ``run.frames_from(T - T')`` when only the last T'
        frames' outputs are wanted (the last block of a forward with context-only frames)."""
        out = out or run
        first = run.t - out.t
        text_kv, control_kv = cross
        m = (run.mod + self.modulation)[:, None, :, None]  # (B, 1, T, 1, 6, D)
        shift1, scale1, gate1, shift2, scale2, gate2 = m.unbind(dim=-2)

        h = torch.addcmul(shift1, self._per_frame(self.norm1(x), run), 1 + scale1).view_as(x)
        a, kv = self.attn(h, run.cos, run.sin, run.self_mask, context, queries_from=first * run.n)
        if first:
            x = self._per_frame(x, run)[:, :, first:].reshape(run.b * run.v, out.t * run.n, x.shape[-1])
            gate1, shift2, scale2, gate2 = (g[:, :, first:] for g in (gate1, shift2, scale2, gate2))
            control_kv = (run.frame_rows(control_kv[0], first), run.frame_rows(control_kv[1], first))
            if out.t == 0:
                return x, kv
        run = out
        b, v, t, n = run.b, run.v, run.t, run.n
        x = torch.addcmul(self._per_frame(x, run), self._per_frame(a, run), gate1).view_as(x)

        q = self.norm_text(x).reshape(b, v * t * n, -1)
        x = x + self.text_attn.attend(q, text_kv, run.text_mask).view_as(x)

        # Per frame, all views at once: queries (B*T, V*N); a token of view v, frame f sees sensor v
        # and the controls of frame f only.
        q = self._frame_major(self.norm_control(x), run)
        out = self.control_attn.attend(q, control_kv, run.control_mask)
        x = x + self._view_major(out, run)

        if self.cross_view is not None:
            hv = self._frame_major(self.norm_view(x), run)
            x = x + self._view_major(self.cross_view(hv, hv, run.view_mask), run)

        h = torch.addcmul(shift2, self._per_frame(self.norm2(x), run), 1 + scale2).view_as(x)
        h = self.fc2(F.gelu(self.fc1(h)))
        x = torch.addcmul(self._per_frame(x, run), self._per_frame(h, run), gate2).view_as(x)
        return x, kv


class MultiViewDiT(nn.Module):
    """Velocity network v_theta(x_t, t; C) over all views (see module docstring)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        # bf16 autocast: the config's, unless built inside precision.dit_precision (training's dtype).
        self.autocast_bf16 = built_autocast_bf16(cfg.dit.autocast_bf16)
        d, p, c = cfg.dit.dim, cfg.dit.patch, cfg.vae.latent_channels
        self.tokenizer = ControlTokenizer(cfg)
        self.patch_in = nn.Linear((c + cfg.layout.channels + cfg.dit.in_channels_extra) * p * p, d)
        self.view_type = nn.Parameter(torch.zeros(2, d))  # camera, LiDAR
        # Fixed 2-D sin-cos embedding of (row, col): RoPE alone is relative, and a view's layout
        # (sky on top, road below, LiDAR beams by elevation) is absolute. Frames get no absolute
        # embedding so a streaming rollout is shift-invariant in time.
        self.register_buffer("spatial_embed", _sincos_2d(d, *cfg.token_hw), persistent=False)
        self.time_embed = TimestepEmbedding(d, cfg.dit.timestep_freq_dim, cfg.dit.timestep_scale)
        self.time_proj = nn.Linear(d, MODULATIONS * d)
        self.blocks = nn.ModuleList(DiTBlock(cfg, i in cfg.cross_view_blocks) for i in range(cfg.dit.depth))
        self.norm_out = nn.LayerNorm(d, elementwise_affine=False, eps=cfg.dit.norm_eps)
        self.out_mod = nn.Linear(d, 2 * d)
        self.head = nn.Linear(d, c * p * p)
        # adaLN-Zero: every block and the output start as identity / zero.
        for lin in (self.time_proj, self.out_mod, self.head):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)

    def _autocast(self, device_type: str) -> AbstractContextManager[None]:
        return bf16_autocast(device_type, self.autocast_bf16)

    def compile_blocks(self) -> None:
        """``torch.compile`` every block's forward (inductor, static shapes): fuses the norms,
        modulation, RoPE and softmax around the matmuls. Opt-in: the first calls of each shape
        compile (tens of seconds on CPU) and inductor needs a C++ compiler at run time. Applying or
        removing a LoRA adapter swaps modules, so the blocks recompile."""
        import torch._dynamo

        # One graph per (block kind, chunk/context shape): a rollout's first chunks see shorter
        # contexts, so allow more graphs than dynamo's default before it falls back to eager.
        torch._dynamo.config.cache_size_limit = max(torch._dynamo.config.cache_size_limit, 64)
        for block in self.blocks:
            block.forward = torch.compile(block.forward, dynamic=False)

    def tokenize(self, cond: Conditions) -> ControlTokens:
        """Control tokens for ``cond`` with every block's cross-attention keys/values; pass them to
        :meth:`forward` to reuse across denoising steps (they depend on the controls only)."""
        with self._autocast(cond.ego.device.type):
            tokens = self.tokenizer(cond)
            tokens.cross_kv = [block.cross_kv(tokens) for block in self.blocks]
            return tokens

    def _check(self, x: torch.Tensor, t: torch.Tensor, hooks: _Hooks) -> torch.Tensor:
        """Refuse inputs of the wrong shape; ``t`` as (B, T)."""
        cfg = self.cfg
        want = (cfg.sensors.num_views, cfg.vae.latent_channels + cfg.dit.in_channels_extra, *cfg.latent_hw)
        if x.ndim != 6 or tuple(x.shape[2:]) != want:
            raise ValueError(f"x must be (B, T, V, C, h, w) with (V, C, h, w) = {want}, got {tuple(x.shape)}")
        b, t_len = x.shape[:2]
        if t.ndim == 1:
            t = t[:, None].expand(b, t_len)
        if t.shape != (b, t_len):
            raise ValueError(f"t must be (B,) or (B, T) = {(b, t_len)}, got {tuple(t.shape)}")
        if not 0 <= hooks.context_only_frames <= t_len:
            raise ValueError(f"context_only_frames must be in [0, {t_len}], got {hooks.context_only_frames}")
        if hooks.kv_context is not None and len(hooks.kv_context) != len(self.blocks):
            raise ValueError(f"kv_context needs one (k, v) per block ({len(self.blocks)}), got {len(hooks.kv_context)}")
        if hooks.blocks is not None and hooks.blocks.shape != (t_len,):
            raise ValueError(f"blocks must be ({t_len},) block indices, got {tuple(hooks.blocks.shape)}")
        return t

    # function-size: ten keyword-only hooks, the streaming engine's; the steps are the methods below
    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond: Conditions | ControlTokens,
        *,
        causal: bool = False,
        frame_offset: int = 0,
        kv_context: list[KV] | None = None,
        return_kv: bool = False,
        blocks: torch.Tensor | None = None,
        context_valid: torch.Tensor | None = None,
        context_only_frames: int = 0,
    ) -> torch.Tensor | tuple[torch.Tensor, list[KV]]:
        """Predict the velocity.

        Args:
            x: (B, T, V, C + in_channels_extra, h, w) noisy latents (+ reference channels).
            t: (B,) or (B, T) flow time per sample or per frame (1 = clean).
            cond: conditions, or control tokens already computed for them (T frames).
            causal: block-causal attention over chunks of ``clip.chunk_frames`` frames.
            frame_offset: RoPE frame index of the first frame of ``x``.
            kv_context: per block, cached self-attention (k, v) (B*V, H, Sc, hd) of earlier frames.
            return_kv: also return each block's own (k, v) for caching.
            blocks: (T,) non-decreasing block index per frame for ``causal`` (default: chunks of
                ``clip.chunk_frames``); a streaming rollout's conditioning frames form block 0.
            context_valid: (B, Sc / N) bool, which ``kv_context`` frames each sample may attend to
                (rollouts of one batch restarted at different times); default all.
            context_only_frames: the first frames of ``x`` only give keys/values to the others
                (the refreshed context frame of the causal student; all T for a pure K/V pass):
                the last block skips their queries and everything after its self-attention, and
                their velocity is not returned.
        Returns:
            velocity (B, T - context_only_frames, V, C, h, w) float32 [and the list of per-block
            (k, v) of all T frames].
        """
        hooks = _Hooks(causal, frame_offset, kv_context, return_kv, blocks, context_valid, context_only_frames)
        t = self._check(x, t, hooks)
        with self._autocast(x.device.type):
            tokens = cond if isinstance(cond, ControlTokens) else self.tokenizer(cond)
            if tokens.frame.shape[1] != x.shape[1]:
                raise ValueError(f"conditions have {tokens.frame.shape[1]} frames, latents {x.shape[1]}")
            h = self._embed_patches(x, tokens)
            temb = self.time_embed(t)  # (B, T, D)
            run = self._run_state(x, h, tokens, temb, hooks)
            h, kvs = self._run_blocks(h, run, tokens, hooks)
            out = self._velocity(h, temb, run, hooks.context_only_frames)
        return (out, kvs) if return_kv else out

    def _embed_patches(self, x: torch.Tensor, tokens: ControlTokens) -> torch.Tensor:
        """Latents (B, T, V, C, h, w), the layout's channels put in after the latent's, -> each view's
        tokens (B*V, T*N, D) with their spatial and view-type embeddings."""
        cfg = self.cfg
        b, t_len, v = x.shape[:3]
        c_lat, p, (th, tw) = cfg.vae.latent_channels, cfg.dit.patch, cfg.token_hw
        n = th * tw
        if cfg.layout.channels:
            x = torch.cat([x[:, :, :, :c_lat], tokens.layout.to(x.dtype), x[:, :, :, c_lat:]], dim=3)
        cin = x.shape[3]
        h = x.permute(0, 2, 1, 3, 4, 5).reshape(b, v, t_len, cin, th, p, tw, p)
        h = h.permute(0, 1, 2, 4, 6, 3, 5, 7).reshape(b, v, t_len * n, cin * p * p)
        view_type = torch.zeros(v, dtype=torch.long, device=x.device)
        view_type[cfg.sensors.lidar_view] = 1
        h = self.patch_in(h.to(self.patch_in.weight.dtype)).view(b, v, t_len, n, -1)
        h = h + self.spatial_embed.to(h.dtype)
        return (h + self.view_type[view_type][None, :, None, None]).reshape(b * v, t_len * n, -1)

    def _run_state(
        self, x: torch.Tensor, h: torch.Tensor, tokens: ControlTokens, temb: torch.Tensor, hooks: _Hooks
    ) -> _Run:
        """The state every block reads: the timestep modulation, RoPE tables from ``frame_offset`` on
        and the attention masks, as biases in the compute dtype of the embedded tokens ``h``."""
        cfg = self.cfg
        b, t_len, v = x.shape[:3]
        th, tw = cfg.token_hw
        n, dt = th * tw, h.dtype
        mod = self.time_proj(F.silu(temb)).unflatten(-1, (MODULATIONS, -1))
        cos, sin = rope_tables(cfg.dit.head_dim, t_len, th, tw, hooks.frame_offset, cfg.dit.rope_theta, x.device)
        cos, sin = rotation_tables(cos, sin, dt)
        view_mask = cross_view_mask(tokens.view_adjacency, n)[:, None].expand(b, t_len, -1, -1)
        return _Run(
            b=b,
            v=v,
            t=t_len,
            n=n,
            mod=mod,
            cos=cos,
            sin=sin,
            self_mask=mask_bias(self._self_mask(hooks, t_len, v, x.device), dt),
            tokens=tokens,
            text_mask=mask_bias(tokens.text_mask[:, None, None], dt),
            control_mask=mask_bias(_control_mask(tokens, n), dt),
            view_mask=mask_bias(view_mask.reshape(b * t_len, 1, v * n, v * n), dt),
        )

    def _self_mask(self, hooks: _Hooks, t_len: int, v: int, device: torch.device) -> torch.Tensor | None:
        """The self-attention's mask (None: every token sees every token): block-causal when
        ``causal`` spans more than one chunk, and each sample's valid context frames."""
        cfg = self.cfg
        n = cfg.tokens_per_frame
        ctx_frames = 0 if hooks.kv_context is None else hooks.kv_context[0][0].shape[2] // n
        blocks = hooks.blocks
        mask = None
        many = t_len > cfg.clip.chunk_frames if blocks is None else bool(blocks[-1] > blocks[0])
        if hooks.causal and many:  # one chunk sees all of itself: no mask needed
            mask = block_causal_mask(t_len, n, cfg.clip.chunk_frames, ctx_frames, device, blocks)
        if hooks.context_valid is not None:
            mask = _context_mask(mask, hooks.context_valid, t_len, n, v)
        return mask

    def _run_blocks(
        self, h: torch.Tensor, run: _Run, tokens: ControlTokens, hooks: _Hooks
    ) -> tuple[torch.Tensor, list[KV]]:
        """The blocks over the tokens ``h`` (B*V, T*N, D); the last one keeps the frames after the
        context-only ones. Also each block's self-attention (k, v) with ``return_kv``."""
        cross = tokens.cross_kv or [block.cross_kv(tokens) for block in self.blocks]
        kvs: list[KV] = []
        last = len(self.blocks) - 1
        out_run = run.frames_from(hooks.context_only_frames) if hooks.context_only_frames else None
        # What shapes the blocks' linears and attention products (adapters' linears see the same rows).
        context = None if hooks.kv_context is None else tuple(hooks.kv_context[0][0].shape)
        shapes = (tuple(h.shape), hooks.context_only_frames, context, *(tuple(kv[0].shape) for kv in cross[0]))
        with whole_if_split_free(self, shapes):
            for i, block in enumerate(self.blocks):
                ctx = None if hooks.kv_context is None else hooks.kv_context[i]
                h, kv = block(h, run, ctx, cross[i], out_run if i == last else None)
                if hooks.return_kv:
                    kvs.append(kv)
        return h, kvs

    def _velocity(self, h: torch.Tensor, temb: torch.Tensor, run: _Run, first: int) -> torch.Tensor:
        """The last block's tokens of frames ``first``.. -> their velocity (B, T - first, V, C, h, w) float32."""
        cfg = self.cfg
        b, v, n, t_out = run.b, run.v, run.n, run.t - first
        p, (th, tw), c = cfg.dit.patch, cfg.token_hw, cfg.vae.latent_channels
        shift, scale = self.out_mod(F.silu(temb[:, first:]))[:, None, :, None].chunk(2, dim=-1)
        h = self.norm_out(h).view(b, v, t_out, n, h.shape[-1]) * (1 + scale) + shift
        out = self.head(h).float()  # (B, V, T', N, C*p*p)
        out = out.reshape(b, v, t_out, th, tw, c, p, p).permute(0, 2, 1, 5, 3, 6, 4, 7)
        return out.reshape(b, t_out, v, c, th * p, tw * p)
