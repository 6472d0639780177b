"""``--stage reference`` (§6): the reference-conditioned model, initialized from the teacher.

Layout::

    RUN_DIR/reference/   checkpoints/, model.safetensors + model.json (EMA weights;
                         model_config has in_channels_extra = C + 1, "reference" the task mix)

The model starts as ``RUN_DIR/teacher/model`` with zero-initialized reference input channels
(:func:`~world_model.model.reference.expand_teacher`), so step 0 computes the teacher exactly.
Each training example draws its task from :class:`~world_model.model.reference.ReferenceConfig`
(unconditional 10%, first frame all views 30%, first frame single view 30%, object completion
30%); a batch is cut to its first frame with ``first_frame_only_prob`` (the env's reset()).
The flow-matching loss covers the whole latent, observed regions included: copying them is part
of what the model must learn. Load the export with :func:`~world_model.train.load_teacher`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig
from world_model.model.flow import flow_matching_loss, sample_timesteps
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.reference import (
    TASKS,
    ReferenceConfig,
    expand_teacher,
    reference_input,
    reference_model_config,
    task_mask,
)
from world_model.model.text import make_text_encoder
from world_model.model.vae import SensorVAE
from world_model.train.checkpoint import export_weights
from world_model.train.data import LatentWindows, cached_latents, file_digest, latent_cache_dir, load_clips
from world_model.train.stages import EXPORT, load_teacher, load_vae
from world_model.train.trainer import TrainConfig, Trainer


def run_vae(run_dir: Path, cfg: ModelConfig, stage: str) -> tuple[SensorVAE, str]:
    """The run's VAE export, checked against ``cfg``; actionable errors otherwise."""
    path = run_dir / "vae" / EXPORT
    if not path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(f"--stage {stage} needs a trained VAE at {path}.safetensors; run --stage vae first")
    vae = load_vae(path)
    if vae.cfg.vae.model_settings() != cfg.vae.model_settings() or vae.cfg.sensors != cfg.sensors:
        raise ValueError(f"the VAE in {path.parent} was trained for preset {vae.cfg.name!r}, not {cfg.name!r}")
    return vae, file_digest(path.with_suffix(".safetensors"))


def sample_windows(
    windows: LatentWindows,
    rng: np.random.Generator,
    batch: int,
    frames: int | None = None,
    clips: Sequence[int] | None = None,
) -> tuple[torch.Tensor, Conditions, list[tuple[int, int, int]]]:
    """Like ``LatentWindows.sample`` but also returns each window's (clip, start, frames).

    ``frames`` fixes the length (default: drawn from ``clip.train_frames``); ``clips`` restricts
    the clips drawn from (indices, default all).
    """
    pool = list(range(len(windows.clips))) if clips is None else list(clips)
    lengths = {i: windows.clips[i].num_frames for i in pool}
    t = frames if frames is not None else int(rng.choice(windows.cfg.clip.train_frames))
    eligible = [i for i in pool if lengths[i] >= t]
    if not eligible:  # every clip is shorter: use the longest available length
        t = max(lengths.values())
        eligible = [i for i in pool if lengths[i] == t]
    picks = [int(c) for c in rng.choice(eligible, size=batch)]
    spans = [(ci, int(rng.integers(lengths[ci] - t + 1)), t) for ci in picks]
    items = [windows.window(ci, s, n) for ci, s, n in spans]
    return torch.stack([x for x, _ in items]).float(), Conditions.collate([a for _, a in items]), spans


def reference_batch(
    windows: LatentWindows, rng: np.random.Generator, batch: int, rcfg: ReferenceConfig
) -> tuple[torch.Tensor, Conditions, torch.Tensor, list[str]]:
    """x0 (B, T, V, C, h, w), conditions, reference channels (B, T, V, C + 1, h, w), task names."""
    cfg = windows.cfg
    frames = 1 if rng.random() < rcfg.first_frame_only_prob else None
    x0, cond, spans = sample_windows(windows, rng, batch, frames)
    tasks = [TASKS[int(rng.choice(len(TASKS), p=rcfg.task_probs))] for _ in spans]
    masks = [
        task_mask(task, cfg, windows.clips[ci].frames[s : s + n], rng, rcfg)
        for task, (ci, s, n) in zip(tasks, spans, strict=True)
    ]
    return x0, cond, reference_input(x0, torch.from_numpy(np.stack(masks))), tasks


def reference_stage(
    data_dir: Path,
    stage_dir: Path,
    cfg: ModelConfig,
    tcfg: TrainConfig,
    progress: bool,
    rcfg: ReferenceConfig | None = None,
) -> dict:
    """Train (or resume) the reference model of ``stage_dir.parent`` (see module docstring)."""
    rcfg = rcfg or ReferenceConfig()
    run_dir = stage_dir.parent
    teacher_path = run_dir / "teacher" / EXPORT
    if not teacher_path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(
            f"--stage reference starts from the teacher at {teacher_path}.safetensors; run --stage teacher first"
        )
    vae, digest = run_vae(run_dir, cfg, "reference")
    teacher = load_teacher(teacher_path)
    if teacher.cfg.teacher_settings() != cfg.teacher_settings():
        raise ValueError(
            f"the teacher in {teacher_path.parent} has preset {teacher.cfg.name!r}'s config, not {cfg.name!r}'s"
        )
    clips = load_clips(data_dir, cfg)
    latents = [cached_latents(c, vae, latent_cache_dir(stage_dir.parent), digest) for c in clips]
    windows = LatentWindows(clips, latents, cfg, make_text_encoder(cfg.text), VaeCropEncoder(vae))
    model = expand_teacher(teacher).train()
    ref_cfg = reference_model_config(cfg)
    meta = {"stage": "reference", "model_config": ref_cfg.to_dict(), "reference": asdict(rcfg)}
    trainer = Trainer(stage_dir, model, tcfg, meta, progress)
    counts = dict.fromkeys(TASKS, 0)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        x0, cond, extra, tasks = reference_batch(windows, tr.rng, tcfg.batch_size, rcfg)
        for task in tasks:
            counts[task] += 1
        b = x0.shape[0]
        cond = cond.with_drop(torch.rand(b, generator=tr.gen) < cfg.flow.cond_drop_prob)
        t = sample_timesteps((b,), cfg.flow, tr.gen)
        noise = torch.randn(x0.shape, generator=tr.gen)
        loss = flow_matching_loss(lambda xt, tt: model(torch.cat([xt, extra], dim=3), tt, cond), x0, t, noise)
        return loss, b * x0.shape[1]

    summary = trainer.run(step, "reference")
    export_weights(
        stage_dir / EXPORT,
        trainer.ema.model_state(model),
        {**meta, "step": trainer.step, "teacher_sha256": file_digest(teacher_path.with_suffix(".safetensors"))},
    )
    return {**summary, "task_counts": counts}
