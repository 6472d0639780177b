"""A tiny DiT overfits one clip in seconds with the shared flow-matching loss."""

import numpy as np
import torch

from tests.model_fixtures import make_sensors, tiny_conditions
from world_model.model import (
    Conditions,
    MultiViewDiT,
    SensorVAE,
    flow_matching_loss,
    get_preset,
    sample_timesteps,
)

LOSS_DROP_FACTOR = 4.0  # measured ~6 with these settings
STEPS = 250
BATCH = 4


def test_tiny_dit_overfits_one_clip():
    cfg = get_preset("tiny")
    torch.manual_seed(0)
    vae = SensorVAE(cfg).eval()
    cams, lidar, _ = make_sensors(cfg, 2)
    x0 = vae.encode_frames(cams, lidar.astype(np.float32))[None]
    x0 = (x0 - x0.mean()) / x0.std()  # unit scale, as the trained VAE's latent normalization gives
    cond = tiny_conditions(cfg, 2)
    model = MultiViewDiT(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    batch_cond = Conditions.cat([cond] * BATCH)
    gen = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(STEPS):
        t = sample_timesteps((BATCH,), cfg.flow, gen)
        batch = x0.expand(BATCH, *x0.shape[1:])
        loss = flow_matching_loss(
            lambda xt, tt: model(xt, tt, batch_cond), batch, t, torch.randn(batch.shape, generator=gen)
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    first, last = np.mean(losses[:10]), np.mean(losses[-20:])
    assert first / last > LOSS_DROP_FACTOR, (first, last)
