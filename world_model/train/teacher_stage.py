"""``--stage teacher`` (§4.1, bidirectional mid-training): the multi-view DiT trained with
rectified flow on windows of the run's cached latents.

Layout: ``RUN/teacher/`` holds checkpoints/, latents/ (the run's latent cache, shared by every
stage) and model.safetensors + model.json (EMA weights). Reads the run's VAE export.
"""

from __future__ import annotations

import torch

from world_model.model.dit import MultiViewDiT
from world_model.model.flow import flow_matching_loss, sample_timesteps
from world_model.train.checkpoint import export_weights
from world_model.train.exports import EXPORT
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer


def teacher_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/teacher`` (module docstring)."""
    cfg, tcfg = run.cfg, run.tcfg
    windows = run.latents("teacher")
    torch.manual_seed(tcfg.seed)
    model = MultiViewDiT(cfg)
    trainer = run.trainer(model, "teacher")

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        x0, cond = windows.sample(tr.rng, tcfg.batch_size)
        b = x0.shape[0]
        drop = tr.rand(b) < cfg.flow.cond_drop_prob
        t = sample_timesteps((b,), cfg.flow, tr.gen)
        noise = tr.randn(*x0.shape)
        x0, cond, t, noise = tr.shard(x0), tr.shard(cond).with_drop(tr.shard(drop)), tr.shard(t), tr.shard(noise)
        loss = flow_matching_loss(lambda xt, tt: model(xt, tt, cond), x0, t, noise)
        return loss, x0.shape[0] * x0.shape[1]

    summary = trainer.run(step, "teacher")
    if run.place.is_main:
        export_weights(
            run.stage_dir / EXPORT,
            trainer.ema.model_state(model),
            {"stage": "teacher", "step": trainer.step, "model_config": cfg.to_dict()},
        )
    return summary
