"""Rectified flow + Euler sampler on a 2-D Gaussian mixture; CFG and APG formulas."""

import numpy as np
import torch
from torch import nn

from world_model.model.config import FlowConfig
from world_model.model.flow import euler_sample, flow_matching_loss, interpolate, predict_x0, sample_timesteps
from world_model.model.guidance import AdaptiveProjectedGuidance, cfg_combine, project

MODES = torch.tensor([[2.0, 2.0], [-2.0, 2.0], [-2.0, -2.0], [2.0, -2.0]])
WEIGHTS = torch.tensor([0.4, 0.3, 0.2, 0.1])
STD = 0.25


class VelocityMLP(nn.Module):
    def __init__(self, width: int = 128) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(2 + 16, width),
            nn.SiLU(),
            nn.Linear(width, width),
            nn.SiLU(),
            nn.Linear(width, width),
            nn.SiLU(),
            nn.Linear(width, 2),
        )
        self.register_buffer("freqs", torch.arange(1, 9).float() * torch.pi)

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        ang = t[:, None] * self.freqs
        return self.net(torch.cat([x, ang.sin(), ang.cos()], dim=1))


def sample_data(n: int, gen: torch.Generator) -> torch.Tensor:
    idx = torch.multinomial(WEIGHTS, n, replacement=True, generator=gen)
    return MODES[idx] + STD * torch.randn(n, 2, generator=gen)


def test_flow_matching_recovers_gaussian_mixture():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    net = VelocityMLP()
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    cfg = FlowConfig(timestep_dist="logit_normal")
    for _ in range(1500):
        x0 = sample_data(256, gen)
        t = sample_timesteps((256,), cfg, gen)
        loss = flow_matching_loss(net, x0, t, torch.randn(256, 2, generator=gen))
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        x = euler_sample(net, torch.randn(4000, 2, generator=gen), steps=50)
    dist = torch.cdist(x, MODES)
    nearest = dist.argmin(dim=1)
    mass = torch.bincount(nearest, minlength=4).float() / len(x)
    # Per-mode mass error below 0.05 and samples land on the modes (within 3 std).
    assert (mass - WEIGHTS).abs().max() < 0.05, mass
    assert (dist.min(dim=1).values < 3 * STD).float().mean() > 0.9


def test_interpolation_convention_t1_is_data():
    x0, eps = torch.ones(3, 2), torch.zeros(3, 2)
    assert torch.equal(interpolate(x0, eps, torch.ones(3)), x0)
    assert torch.equal(interpolate(x0, eps, torch.zeros(3)), eps)
    v = x0 - eps
    xt = interpolate(x0, eps, torch.full((3,), 0.3))
    assert torch.allclose(predict_x0(xt, v, torch.full((3,), 0.3)), x0)


def test_timestep_distributions_in_unit_interval_and_shift_moves_mass_to_noise():
    gen = torch.Generator().manual_seed(0)
    base = sample_timesteps((20000,), FlowConfig(), gen)
    shifted = sample_timesteps((20000,), FlowConfig(shift=3.0), torch.Generator().manual_seed(0))
    assert base.min() > 0 and base.max() < 1
    assert shifted.mean() < base.mean() - 0.1


def test_cfg_formula():
    vc, vu = torch.randn(4, 3), torch.randn(4, 3)
    assert torch.allclose(cfg_combine(vc, vu, 1.0), vc)
    assert torch.allclose(cfg_combine(vc, vu, 3.0), vu + 3.0 * (vc - vu))


def test_apg_removes_parallel_component():
    gen = torch.Generator().manual_seed(0)
    dc, du = torch.randn(2, 4, 5, 6, generator=gen), torch.randn(2, 4, 5, 6, generator=gen)
    apg = AdaptiveProjectedGuidance(scale=4.0, eta=0.0, norm_threshold=0.0, momentum=0.0)
    out = apg(dc, du)
    # Formula by hand, per sample over the last three dims.
    diff = (dc - du).flatten(1)
    unit = dc.flatten(1) / dc.flatten(1).norm(dim=1, keepdim=True)
    orth = diff - (diff * unit).sum(dim=1, keepdim=True) * unit
    assert torch.allclose(out.flatten(1), dc.flatten(1) + 3.0 * orth, atol=1e-5)
    # The guidance update has no component along the conditional prediction.
    update = (out - dc).flatten(1)
    assert torch.allclose((update * unit).sum(dim=1), torch.zeros(2), atol=1e-4)
    # eta = 1 and no threshold is plain CFG on the denoised predictions.
    full = AdaptiveProjectedGuidance(scale=4.0, eta=1.0)(dc, du)
    assert torch.allclose(full, du + 4.0 * (dc - du), atol=1e-5)


def test_apg_norm_threshold_and_momentum():
    dc, du = torch.zeros(1, 1, 1, 2), torch.zeros(1, 1, 1, 2)
    dc[..., 0], du[..., 1] = 1.0, 10.0  # diff = (1, -10): orthogonal part (0, -10)
    out = AdaptiveProjectedGuidance(scale=2.0, norm_threshold=1.0)(dc, du)
    par, orth = project(torch.tensor([[[[1.0, -10.0]]]]) / np.hypot(1, 10), dc, (-1, -2, -3))
    assert torch.allclose(out, dc + orth, atol=1e-6)
    apg = AdaptiveProjectedGuidance(scale=2.0, eta=1.0, momentum=-0.5)
    first = apg(dc, du)
    second = apg(dc, du)  # running = diff - 0.5 * diff = 0.5 diff
    assert torch.allclose(second - dc, 0.5 * (first - dc), atol=1e-6)


def test_weighted_flow_loss_is_the_weighted_mean_of_squared_errors():
    gen = torch.Generator().manual_seed(0)
    x0, noise = torch.randn(3, 4, 5, generator=gen), torch.randn(3, 4, 5, generator=gen)
    t = torch.rand(3, generator=gen)
    bias = torch.randn(3, 4, 5, generator=gen)

    def net(xt, tt):
        return x0 - noise + bias  # error = bias

    plain = flow_matching_loss(net, x0, t, noise)
    assert torch.allclose(flow_matching_loss(net, x0, t, noise, torch.ones(3, 1, 5)), plain)
    w = torch.rand(3, 4, 1, generator=gen) + 0.5  # broadcast over the last dim
    want = (bias.pow(2) * w).sum() / w.expand_as(bias).sum()
    assert torch.allclose(flow_matching_loss(net, x0, t, noise, w), want)
    # Zero weight: the errors there do not count at all.
    w0 = torch.ones(3, 4, 5)
    w0[:, :2] = 0.0

    def worse(xt, tt):
        out = net(xt, tt).clone()
        out[:, :2] += 100.0
        return out

    assert torch.allclose(flow_matching_loss(worse, x0, t, noise, w0), flow_matching_loss(net, x0, t, noise, w0))
