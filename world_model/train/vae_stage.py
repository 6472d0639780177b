"""``--stage vae``: the camera/LiDAR autoencoder, trained on random sensor frames.

Layout: ``RUN/vae/`` holds checkpoints/, model.safetensors + model.json (EMA weights, latent
statistics, reconstruction metrics) and metrics.json.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from world_model.data.clips import write_json_atomic
from world_model.model.vae import SensorVAE, images_to_cameras, images_to_lidar, kl_loss, weighted_l1
from world_model.train.checkpoint import export_weights
from world_model.train.data import FrameSampler, load_clips
from world_model.train.exports import EXPORT
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer

EVAL_FRAMES = 32  # frames used for the VAE's reconstruction metrics
STATS_FRAMES = 64  # frames used to fit the latent normalization


@torch.no_grad()
def vae_metrics(vae: SensorVAE, sampler: FrameSampler) -> dict[str, float]:
    """Camera PSNR (dB, uint8 images) and LiDAR range MAE (m, on true returns) + no-return accuracy."""
    cfg = vae.cfg
    spec = cfg.sensors.lidar
    device = next(vae.parameters()).device
    se, count, abs_err, n_ret, nr_ok, n_all = 0.0, 0, 0.0, 0, 0, 0
    for ci, f in sampler.eval_frames(EVAL_FRAMES):
        clip = sampler.clips[ci]
        cams = np.asarray(clip.cameras[f])
        x = torch.stack([sampler.image(ci, f, v) for v in range(cfg.sensors.num_views)]).to(device)
        rec = vae.decode(vae.encode(x)).float().cpu()
        se += float(((images_to_cameras(rec[:-1]).astype(np.float64) - cams) ** 2).sum())
        count += cams.size
        truth = np.asarray(clip.lidar[f], dtype=np.float32)
        pred = images_to_lidar(rec[-1], spec, cfg.vae.lidar_no_return_fraction)
        ret = truth > spec.no_return
        abs_err += float(np.abs(pred - truth)[ret].sum())
        n_ret += int(ret.sum())
        nr_ok += int(((pred > spec.no_return) == ret).sum())
        n_all += truth.size
    mse = se / max(count, 1)
    return {
        "camera_psnr_db": 10 * math.log10(255.0**2 / max(mse, 1e-10)),
        "lidar_range_mae_m": abs_err / max(n_ret, 1),
        "lidar_return_accuracy": nr_ok / max(n_all, 1),
    }


def vae_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/vae`` (module docstring)."""
    cfg, tcfg = run.cfg, run.tcfg
    sampler = FrameSampler(load_clips(run.data_dir, cfg), cfg)
    torch.manual_seed(tcfg.seed)
    vae = SensorVAE(cfg)
    trainer = run.trainer(vae, "vae")

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        batch = sampler.sample(tr.rng, tcfg.batch_size)
        images, is_lidar, weights = tr.shard(batch.images), tr.shard(batch.is_lidar), tr.shard(batch.weights)
        mean, logvar = vae.posterior(images)
        eps = tr.shard(tr.randn(tcfg.batch_size, *mean.shape[1:]))
        z = mean + (0.5 * logvar).exp() * eps
        err = weighted_l1(vae.decode_raw(z), images, weights)
        weight = torch.where(is_lidar, cfg.vae.lidar_loss_weight, 1.0)
        return (err * weight).mean() + cfg.vae.kl_weight * kl_loss(mean, logvar), len(images)

    summary = trainer.run(step, "vae")
    if not run.place.is_main:
        return summary
    final = SensorVAE(cfg)
    final.load_state_dict(trainer.ema.model_state(vae))
    stats_rng = np.random.default_rng(tcfg.seed)
    final.set_latent_stats(sampler.sample(stats_rng, STATS_FRAMES).images)
    final.eval()
    metrics = vae_metrics(final, sampler)
    export_weights(
        run.stage_dir / EXPORT,
        final.state_dict(),
        {"stage": "vae", "step": trainer.step, "model_config": cfg.to_dict(), "metrics": metrics},
    )
    write_json_atomic(run.stage_dir / "metrics.json", {"step": trainer.step, **metrics})
    return {**summary, "metrics": metrics}
