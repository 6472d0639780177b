"""``--stage first_frame``: the one-step first-frame model, distilled from the reference model.

Layout::

    RUN_DIR/first_frame/  checkpoints/, pool.pt (the frames, their noise and their targets),
                          model.safetensors + model.json (EMA weights; the reference model's config)

``env.reset()`` draws an episode's first frame from controls with the reference model: the
bundle's ``first_frame_steps`` Euler steps under classifier-free guidance (two forwards a step),
most of a reset's time. That sampler is deterministic given its noise (Euler, no fresh noise
between steps), so a model can learn the whole map from noise to first frame: this stage trains a
copy of ``RUN_DIR/reference/model`` to give in ONE unguided step, its x0-prediction from pure
noise, what the sampler gives from the same noise, at :class:`~world_model.streaming.StreamingConfig`'s
first-frame settings (those a recipe's bundle streams with).

The targets are sampled once, at the stage's start, for a pool of single frames of the run's
clips (:data:`POOL_FRAMES`, or as many as the clips hold; each with its own noise) and kept in
``pool.pt``: a resumed stage trains on the same pool. The loss is the mean squared error of the
latents. Load the export with :func:`~world_model.train.load_teacher`; it samples as
:data:`~world_model.model.reference.ONE_STEP` says.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import gaussian, predict_x0
from world_model.model.reference import ReferenceGenerator, reference_channels
from world_model.streaming import StreamingConfig
from world_model.train.checkpoint import export_weights
from world_model.train.data import LatentWindows, file_digest
from world_model.train.exports import EXPORT, load_teacher, require_export, run_vae
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer

STAGE = "first_frame"
POOL_FILE = "pool.pt"
# The most frames whose targets the stage samples at its start (no more than the run's clips hold):
# about 0.2 s each at the default preset on a 2-core CPU (the reference model's 4 guided steps).
POOL_FRAMES = 1024
POOL_BATCH = 16  # frames a target-sampling call


def one_step_x0(model: MultiViewDiT, noise: torch.Tensor, cond: Conditions) -> torch.Tensor:
    """``model``'s first frames (B, 1, V, C, h, w) in one step from ``noise`` (same shape), without
    reference images (zero reference channels), as :data:`~world_model.model.reference.ONE_STEP`
    samples them."""
    extra = noise.new_zeros(*noise.shape[:3], reference_channels(model.cfg), *noise.shape[4:])
    t = noise.new_zeros(noise.shape[0])
    return predict_x0(noise, model(torch.cat([noise, extra], dim=3), t, cond).float(), t)


def row_noise(seeds: Sequence[int], cfg: ModelConfig) -> torch.Tensor:
    """First-frame noise (B, 1, V, C, h, w), row i as the reference model draws it for seed ``seeds[i]``."""
    return torch.cat([gaussian((1, *cfg.latent_shape(1)), torch.Generator().manual_seed(int(s))) for s in seeds])


def _pool(run: StageRun, windows: LatentWindows, reference: MultiViewDiT) -> dict[str, torch.Tensor]:
    """The pool (module docstring): ``clips``, ``starts``, the noise ``seeds`` (N,) and the
    ``targets`` (N, 1, V, C, h, w) on the CPU; read from ``pool.pt`` when the stage has one."""
    path = run.stage_dir / POOL_FILE
    if path.exists():
        return torch.load(path, weights_only=True)
    size = min(POOL_FRAMES, int(windows.lengths.sum()))
    clips, starts, _ = windows.draw(np.random.default_rng(run.tcfg.seed), size, 1)
    seeds = run.tcfg.seed + np.arange(size)
    plain, _ = run_vae(run.run_dir, run.cfg, STAGE)
    sampler, streaming = ReferenceGenerator(reference, plain.to(run.place.device)), StreamingConfig()
    targets = []
    for i in range(0, size, POOL_BATCH):
        rows = slice(i, i + POOL_BATCH)
        _, cond = windows.windows(clips[rows], starts[rows], 1)
        first = sampler.sample(
            cond,
            steps=streaming.first_frame_steps,
            seed=[int(s) for s in seeds[rows]],
            guidance=streaming.first_frame_guidance,
        )
        targets.append(first.cpu())
    pool = {
        "clips": torch.as_tensor(clips),
        "starts": torch.as_tensor(starts),
        "seeds": torch.as_tensor(seeds),
        "targets": torch.cat(targets),
    }
    if run.place.is_main:  # every rank samples the same pool; one writes it
        run.stage_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        torch.save(pool, tmp)
        tmp.replace(path)
    return pool


def first_frame_stage(run: StageRun) -> dict:
    """Train (or resume) the first-frame model of ``run.run_dir`` (module docstring)."""
    reference_path = require_export(run.run_dir / "reference" / EXPORT, "reference")
    windows = run.latents(STAGE)
    reference = load_teacher(reference_path).to(run.place.device).eval().requires_grad_(False)
    pool = _pool(run, windows, reference)
    model = load_teacher(reference_path).train().requires_grad_(True)
    streaming = StreamingConfig()
    meta = {
        "model_config": reference.cfg.to_dict(),
        "distilled_from": {"steps": streaming.first_frame_steps, "guidance": streaming.first_frame_guidance},
    }
    trainer = run.trainer(model, STAGE, **meta)
    size = len(pool["targets"])

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        rows = tr.rng.integers(0, size, run.tcfg.batch_size)
        _, cond = windows.windows(pool["clips"].numpy()[rows], pool["starts"].numpy()[rows], 1)
        noise = tr.shard(row_noise(pool["seeds"][rows].tolist(), run.cfg))
        target = tr.shard(pool["targets"][rows])
        return torch.nn.functional.mse_loss(one_step_x0(model, noise, tr.shard(cond)), target), noise.shape[0]

    summary = trainer.run(step, STAGE)
    if run.place.is_main:
        export_weights(
            run.stage_dir / EXPORT,
            trainer.ema.model_state(model),
            {
                "stage": STAGE,
                **meta,
                "step": trainer.step,
                "reference_sha256": file_digest(reference_path.with_suffix(".safetensors")),
            },
        )
    return {**summary, "pool_frames": size}


__all__ = ["POOL_FRAMES", "first_frame_stage", "one_step_x0", "row_noise"]
