"""Model-level pieces of the student stages: teacher forcing, ODE targets, Self-Forcing rollouts,
the DMD generator loss and the critic loss on DiT latents (B, T, V, C, h, w).

Rollout layout (shared with the engine): ``prefix_frames`` clean conditioning frames form causal
block 0, then chunks of ``clip.chunk_frames`` frames (:func:`rollout_blocks`). Teacher forcing
and ODE regression run the causal model over [clean history, noisy target chunk] in ONE forward
with that block mask (history at t = 1), which the engine's cache reproduces chunk by chunk.
"""

from __future__ import annotations

import dataclasses

import torch

from world_model.model.attention import KV
from world_model.model.conditions import Conditions
from world_model.model.config import SamplerConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import flow_matching_loss, interpolate, predict_x0
from world_model.model.sampler import GuidedVelocity
from world_model.student.config import StudentConfig, rollout_blocks
from world_model.student.engine import StreamingEngine
from world_model.student.losses import critic_loss, dmd_loss, ode_grid, ode_trajectory


def teacher_forcing_velocity(
    model: MultiViewDiT,
    history: torch.Tensor,
    x_t: torch.Tensor,
    t: torch.Tensor,
    cond: Conditions,
    prefix: int,
) -> torch.Tensor:
    """Velocity (B, c, ...) of the noisy chunk x_t (time t (B,)) after clean ``history`` (B, F, ...);
    ``cond`` covers all F + c frames."""
    f, c = history.shape[1], x_t.shape[1]
    tt = torch.cat([torch.ones(x_t.shape[0], f, device=x_t.device), t[:, None].expand(-1, c)], dim=1)
    blocks = rollout_blocks(0, f + c, prefix, model.cfg.clip.chunk_frames)
    return model(torch.cat([history, x_t], dim=1), tt, cond, causal=True, blocks=blocks)[:, f:]


def teacher_forcing_loss(
    model: MultiViewDiT, x0: torch.Tensor, cond: Conditions, t: torch.Tensor, noise: torch.Tensor, prefix: int
) -> torch.Tensor:
    """Rectified-flow loss on the last chunk of x0 (B, F + c, ...) given its clean history (§4.2 TF).

    ``noise`` is (B, c, ...) for that chunk.
    """
    c = model.cfg.clip.chunk_frames
    history = x0[:, :-c]
    return flow_matching_loss(
        lambda xt, tt: teacher_forcing_velocity(model, history, xt, tt, cond, prefix), x0[:, -c:], t, noise
    )


@torch.no_grad()
def history_kv(model: MultiViewDiT, history: torch.Tensor, cond: Conditions, prefix: int) -> list[KV]:
    """Per-block K/V of clean history frames (B, F, ...) under the rollout's causal blocks."""
    f = history.shape[1]
    ones = torch.ones(history.shape[0], f, device=history.device)
    blocks = rollout_blocks(0, f, prefix, model.cfg.clip.chunk_frames)
    _, kv = model(history, ones, cond, causal=True, blocks=blocks, return_kv=True)
    return kv


@torch.no_grad()
def ode_targets(
    model: MultiViewDiT,
    history: torch.Tensor,
    cond: Conditions,
    noise: torch.Tensor,
    scfg: StudentConfig,
    sampler: SamplerConfig | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The causal (TF) model's guided Euler ODE for the chunk after ``history`` from ``noise``.

    Runs ``sampler.steps`` Euler steps (grid refined to contain the student's times) with CFG/APG
    (:class:`GuidedVelocity`); the unconditional branch gets the history K/V computed under
    dropped conditions, exactly as the model saw them in training with condition dropout.
    Returns (x at each student time (K, B, c, ...), the endpoint (B, c, ...)).
    """
    sampler = sampler or model.cfg.sampler
    f, c = history.shape[1], noise.shape[1]
    chunk_cond = cond.frames(f, f + c)
    velocity = GuidedVelocity(model, chunk_cond, sampler)
    hist_cond = cond.frames(0, f)
    if velocity.guided:  # each row's history twice, in the rows' order of the guided forward
        both = Conditions.cat([hist_cond, hist_cond.with_drop(True)]).apply(lambda _, v: v[velocity.pairs])
        kv = history_kv(model, torch.cat([history, history])[velocity.pairs], both, scfg.prefix_frames)
    else:
        kv = history_kv(model, history, hist_cond, scfg.prefix_frames)
    velocity.kwargs.update(kv_context=kv, frame_offset=f)
    times = scfg.times()
    return ode_trajectory(velocity, noise, ode_grid(sampler.steps, model.cfg.flow.shift, times), times)


def self_forcing_rollout(
    engine: StreamingEngine,
    first: torch.Tensor,
    cond: Conditions,
    chunks: int,
    exit_step: int | None,
    grad: bool,
) -> torch.Tensor:
    """Roll the student out from clean first frames (B, P, ...) for ``chunks`` chunks with the
    streaming engine; returns [first, generated] (B, P + chunks * c, ...). With ``grad`` only each
    chunk's exit step carries a graph; the cache is written from detached latents."""
    p, c = first.shape[1], engine.cfg.clip.chunk_frames
    engine.start(first, cond.frames(0, p))
    out = [first]
    for k in range(chunks):
        out.append(engine.step(cond.frames(p + k * c, p + (k + 1) * c), exit_step=exit_step, grad=grad))
    return torch.cat(out, dim=1)


def dmd_times(batch: int, scfg: StudentConfig, generator: torch.Generator | None) -> torch.Tensor:
    """(B,) DMD noise times, uniform in [dmd_min_t, dmd_max_t]."""
    return scfg.dmd_min_t + (scfg.dmd_max_t - scfg.dmd_min_t) * torch.rand(
        batch, generator=generator, device=generator.device if generator is not None else None
    )


def real_score_guidance(real: MultiViewDiT, scfg: StudentConfig) -> SamplerConfig:
    """The guidance of the DMD real score: the teacher's sampler, with both scales (camera CFG,
    LiDAR APG) replaced by ``scfg.dmd_guidance_scale`` when that is set."""
    s = scfg.dmd_guidance_scale
    base = real.cfg.sampler
    return base if s is None else dataclasses.replace(base, camera_cfg_scale=s, lidar_apg_scale=s)


def dmd_generator_loss(
    real: MultiViewDiT,
    critic: MultiViewDiT,
    video: torch.Tensor,
    cond: Conditions,
    t: torch.Tensor,
    noise: torch.Tensor,
    skip: int = 0,
    guidance: SamplerConfig | None = None,
) -> torch.Tensor:
    """DMD loss of a generated clip (B, T, ...): real score = the frozen bidirectional teacher with
    guidance (``guidance``'s scales, default the teacher's sampler), fake score = the critic, both as
    x0-predictions at x_t = interpolate(video, noise, t). Frames before ``skip`` (clean conditioning
    frames, not generated) are scored but not trained."""
    with torch.no_grad():
        xt = interpolate(video.detach(), noise, t)
        x0_real = predict_x0(xt, GuidedVelocity(real, cond, guidance)(xt, t), t)
        x0_fake = predict_x0(xt, critic(xt, t, cond), t)
    return dmd_loss(video[:, skip:], x0_fake[:, skip:], x0_real[:, skip:])


def critic_flow_loss(
    critic: MultiViewDiT, video: torch.Tensor, cond: Conditions, t: torch.Tensor, noise: torch.Tensor
) -> torch.Tensor:
    """The fake-score critic's flow loss on a (detached) student clip."""
    return critic_loss(lambda xt, tt: critic(xt, tt, cond), video, t, noise)
