"""The student's losses as small pure functions (shared by the real stages and the toy tests).

Sign convention (paper §4.3, our time convention: t = 1 is data). For ``x_t = t x0 + (1 - t) eps``
the score of the noised distribution is, with ``D(x_t) = E[x0 | x_t]`` the x0-prediction,

    s(x_t) = -(x_t - t D(x_t)) / (1 - t)^2,  so  s_fake - s_real = t / (1 - t)^2 * (D_fake - D_real).

With velocities (``D = x_t + (1 - t) v``), ``D_fake - D_real = (1 - t) (v_fake - v_real)``. The
positive factor is absorbed by DMD's per-sample normalization, so the DMD gradient is

    g = (D_fake - D_real) / mean|x - D_real|       (mean over each sample's elements)

and ``L = 0.5 || x - sg[x - g] ||^2`` has dL/dx = g (per element, up to the 1/numel of the mean):
a gradient step moves the student's sample *toward* the teacher's (real) denoised estimate and
away from the critic's (fake) one -- descending the reverse KL(p_student || p_data).
"""

from __future__ import annotations

import torch

from world_model.model.flow import VelocityFn, euler_integrate, flow_matching_loss, shift_time, weighted_mean

NORM_EPS = 1e-6  # keeps the per-sample DMD normalization finite when the teacher is exact


def dmd_gradient(x: torch.Tensor, x0_fake: torch.Tensor, x0_real: torch.Tensor) -> torch.Tensor:
    """Normalized DMD gradient (B, ...) from the critic's and teacher's x0-predictions at x_t:
    one normalizer per sample (the paper)."""
    diff = (x0_fake - x0_real).double()
    norm = (x - x0_real).double().abs().mean(dim=tuple(range(1, x.ndim)), keepdim=True).clamp_min(NORM_EPS)
    return torch.nan_to_num(diff / norm).to(x.dtype)


def dmd_loss(x: torch.Tensor, x0_fake: torch.Tensor, x0_real: torch.Tensor) -> torch.Tensor:
    """``0.5 * mean((x - sg[x - g])^2)``: gradient g (see module docstring) flows into x only."""
    g = dmd_gradient(x.detach(), x0_fake.detach(), x0_real.detach())
    target = x.detach().double() - g.double()
    return 0.5 * (x.double() - target).pow(2).mean().float()


def critic_loss(critic: VelocityFn, samples: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """The fake-score critic's rectified-flow loss on (detached) student samples."""
    return flow_matching_loss(critic, samples.detach(), t, noise)


def ode_regression_loss(
    x0_pred: torch.Tensor, x0_target: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean squared error of the student's x0-prediction G(x_t, t) to a detached target: the ODE
    trajectory's endpoint (causal ODE initialization). ``weights`` (broadcastable, non-negative): the
    weighted mean instead (:func:`weighted_mean`)."""
    return weighted_mean((x0_pred.float() - x0_target.detach().float()).pow(2), weights)


def ode_grid(teacher_steps: int, shift: float, student_times: torch.Tensor) -> torch.Tensor:
    """The teacher's Euler time grid (``teacher_steps`` steps, SD3 ``shift``), refined so it also
    contains every student time: (M + 1,) increasing from 0 to 1."""
    base = shift_time(torch.linspace(0.0, 1.0, teacher_steps + 1, dtype=torch.float64), shift)
    grid = torch.cat([base, student_times.double()]).unique(sorted=True)
    return grid.float()


@torch.no_grad()
def ode_trajectory(
    velocity_fn: VelocityFn, noise: torch.Tensor, grid: torch.Tensor, record: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Euler-integrate from t = 0 along ``grid``; returns (x at each ``record`` time (K, B, ...),
    the endpoint x at t = 1 (B, ...)). ``velocity_fn`` gets t of shape (B,)."""
    points: dict[float, torch.Tensor] = {}
    want = {round(float(t), 6) for t in record}

    def keep(t: float, x: torch.Tensor) -> None:
        if round(t, 6) in want:
            points[round(t, 6)] = x

    x = euler_integrate(velocity_fn, noise, grid, visit=keep)
    missing = want - set(points)
    if missing:
        raise ValueError(f"record times {sorted(missing)} are not on the grid (use ode_grid)")
    return torch.stack([points[round(float(t), 6)] for t in record]), x
