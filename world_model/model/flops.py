"""Analytic matmul FLOPs of one DiT forward, derived from the config (2 FLOPs per multiply-add).

Counts every matrix product of the token pathway: linear layers (projections, MLP, patch in and
out, timestep embedding) and attention (scores and weighted sums). Elementwise work, norms and
the small tokenizer MLPs are left out.
"""

from __future__ import annotations

from world_model.model.config import ModelConfig


def dit_forward_flops(
    cfg: ModelConfig, batch: int, frames: int, context_frames: int = 0, cross_kv: bool = True
) -> dict[str, int]:
    """{"linear", "attention", "total"} FLOPs of ``MultiViewDiT.forward`` on (batch, frames)
    latents with ``context_frames`` frames of cached keys/values. ``cross_kv=False``: the forward
    is given ``MultiViewDiT.tokenize``'s tokens, which carry the cross-attention keys/values."""
    d, dc, p = cfg.dit.dim, cfg.control.dim, cfg.dit.patch
    v, n = cfg.sensors.num_views, cfg.tokens_per_frame
    cin = (cfg.vae.latent_channels + cfg.layout.channels + cfg.dit.in_channels_extra) * p * p
    cout = cfg.vae.latent_channels * p * p
    hidden = int(d * cfg.dit.mlp_ratio)
    tokens = batch * v * frames * n
    queries = v * frames * n  # per sample, all views
    text = cfg.text.max_tokens + 1  # + the null token
    control = v + 1 + cfg.map_tokens + cfg.control.max_objects + 1  # keys per frame: sensors + controls
    depth, views_blocks = cfg.dit.depth, len(cfg.cross_view_blocks)

    linear_block = (
        4 * tokens * d * d  # self-attention q, k, v, o
        + 2 * tokens * d * d  # text cross-attention q, o
        + 2 * tokens * d * d  # control cross-attention q, o
        + cross_kv * 2 * batch * (text + frames * control) * dc * d  # their k, v
        + 2 * tokens * d * hidden  # MLP
    )
    attention_block = (
        2 * batch * v * (frames * n) * ((frames + context_frames) * n) * d
        + 2 * batch * queries * text * d
        + 2 * batch * frames * (v * n) * control * d
    )
    rows = batch * frames  # the timestep embedding runs once per frame
    timestep = rows * (cfg.dit.timestep_freq_dim * d + d * d + 6 * d * d + 2 * d * d)
    linear = depth * linear_block + views_blocks * 4 * tokens * d * d + tokens * (cin + cout) * d + timestep
    attention = depth * attention_block + views_blocks * 2 * batch * frames * (v * n) ** 2 * d
    return {"linear": 2 * linear, "attention": 2 * attention, "total": 2 * (linear + attention)}
