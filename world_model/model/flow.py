"""Rectified flow (paper §4.1) in the paper's time convention: t = 1 is data, t = 0 is noise.

    x_t = (1 - t) * eps + t * x0,        v* = x0 - eps,        L = || v_theta(x_t, t) - v* ||^2

Everything here takes a generic ``velocity_fn(x_t, t) -> v``, so the DiT, the causal student
and a toy MLP share one loss and one denoising step (:func:`denoise_step`); the Euler sampler is
just that step in a loop. ``t`` is a tensor of leading dims of ``x`` (e.g. (B,) or (B, T) for
latents (B, T, V, C, h, w)) and is broadcast over the remaining dims.

Training timestep distribution (``FlowConfig``): ``uniform`` is the paper's t ~ U(0, 1);
``logit_normal`` (default, SD3) draws t = sigmoid(u), u ~ N(mean, std), concentrating training on
intermediate times where the velocity is hardest to predict. ``shift`` s applies SD3's
resolution shift to the noise level sigma = 1 - t: sigma' = s sigma / (1 + (s - 1) sigma), so s > 1
spends more steps near noise; the same shift spaces the sampler's time grid.

Noise (:func:`gaussian`) is drawn by its generator where the generator lives (a seeded
``torch.Generator()`` is a CPU one) and then moved to the model's device: a seed gives the same
noise on every device, so a GPU rollout and a CPU rollout differ only by their arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from world_model.model.config import FlowConfig

VelocityFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
# A noise source: a torch.Generator (None: torch's global one), or a function shape -> standard
# normal tensor (e.g. one generator per batch row, so a rollout's noise does not depend on the
# other rows of its batch).
NoiseSource = torch.Generator | Callable[[tuple[int, ...]], torch.Tensor] | None


def gaussian(shape: Sequence[int], source: NoiseSource, device: torch.device | str = "cpu") -> torch.Tensor:
    """Standard normal noise of ``shape`` drawn from ``source`` on its own device, on ``device``."""
    if callable(source):
        noise = source(tuple(shape))
    else:
        noise = torch.randn(tuple(shape), generator=source, device=None if source is None else source.device)
    return noise.to(device)


def _bcast(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return t.reshape(*t.shape, *([1] * (x.ndim - t.ndim))).to(x.dtype)


def shift_time(t: torch.Tensor, shift: float) -> torch.Tensor:
    """Apply the SD3 shift to sigma = 1 - t (identity for shift = 1)."""
    sigma = 1.0 - t
    return 1.0 - shift * sigma / (1.0 + (shift - 1.0) * sigma)


def sample_timesteps(
    shape: tuple[int, ...], cfg: FlowConfig, generator: torch.Generator | None = None, device: str = "cpu"
) -> torch.Tensor:
    """Training times in (0, 1) of ``shape`` from ``cfg.timestep_dist``, drawn on the generator's
    device (``device`` without a generator)."""
    on = generator.device if generator is not None else device
    if cfg.timestep_dist == "uniform":
        t = torch.rand(shape, generator=generator, device=on)
    elif cfg.timestep_dist == "logit_normal":
        t = torch.sigmoid(cfg.logit_mean + cfg.logit_std * torch.randn(shape, generator=generator, device=on))
    else:
        raise ValueError(f"unknown timestep_dist {cfg.timestep_dist!r}; use 'uniform' or 'logit_normal'")
    return shift_time(t, cfg.shift).to(on)


def interpolate(x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x_t = (1 - t) noise + t x0."""
    tb = _bcast(t, x0)
    return (1.0 - tb) * noise + tb * x0


def velocity_target(x0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    return x0 - noise


def predict_x0(x_t: torch.Tensor, v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The clean sample implied by a velocity: x0 = x_t + (1 - t) v."""
    return x_t + (1.0 - _bcast(t, x_t)) * v


def flow_matching_loss(
    velocity_fn: VelocityFn,
    x0: torch.Tensor,
    t: torch.Tensor,
    noise: torch.Tensor,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean squared error between v_theta(x_t, t) and x0 - noise.

    ``weights`` (broadcastable to ``x0``, non-negative): the weighted mean sum(w e) / sum(w) instead,
    e.g. more weight inside a rare object's box (the LoRA stage); all ones = the plain mean."""
    v = velocity_fn(interpolate(x0, noise, t), t)
    return weighted_mean((v.float() - velocity_target(x0, noise).float()).pow(2), weights)


def weighted_mean(err: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """The mean of ``err``; with ``weights`` (broadcastable to it, non-negative) sum(w e) / sum(w)."""
    if weights is None:
        return err.mean()
    w = weights.float().expand_as(err)
    return (err * w).sum() / w.sum().clamp_min(torch.finfo(err.dtype).tiny)


def time_grid(steps: int, shift: float = 1.0) -> torch.Tensor:
    """(steps + 1,) increasing times from 0 (noise) to 1 (data)."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    return shift_time(torch.linspace(0.0, 1.0, steps + 1, dtype=torch.float64), shift).float()


def denoise_step(
    velocity_fn: VelocityFn, x: torch.Tensor, t: torch.Tensor, t_next: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One Euler step from t to t_next (same shapes as training's t). Returns (x_next, v)."""
    v = velocity_fn(x, t)
    return x + _bcast(t_next - t, x) * v, v


def euler_integrate(
    velocity_fn: VelocityFn,
    noise: torch.Tensor,
    grid: torch.Tensor,
    t_dims: int = 1,
    visit: Callable[[float, torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """Integrate dx/dt = v from ``grid[0]`` (``noise``) to ``grid[-1]`` with one Euler step per
    interval of ``grid`` (increasing times). The one Euler loop of the project: sampling
    (:func:`euler_sample`) and the causal ODE initialization's teacher trajectories use it.

    ``t_dims`` leading dims of ``noise`` get their own time entry (1: per sample (B,); 2: (B, T)).
    ``visit(t, x)``, when given, sees the state at every grid time before its step.
    """
    grid = grid.to(noise.device)
    x = noise
    lead = noise.shape[:t_dims]
    for i in range(len(grid) - 1):
        if visit is not None:
            visit(float(grid[i]), x)
        x, _ = denoise_step(velocity_fn, x, grid[i].expand(lead), grid[i + 1].expand(lead))
    return x


def euler_sample(
    velocity_fn: VelocityFn, noise: torch.Tensor, steps: int, shift: float = 1.0, t_dims: int = 1
) -> torch.Tensor:
    """Integrate dx/dt = v from t = 0 (``noise``) to t = 1 in ``steps`` Euler steps on the shifted
    grid :func:`time_grid`; ``t_dims`` as :func:`euler_integrate`."""
    return euler_integrate(velocity_fn, noise, time_grid(steps, shift), t_dims)
