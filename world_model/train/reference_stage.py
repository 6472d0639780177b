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

import numpy as np
import torch

from world_model.model.conditions import Conditions
from world_model.model.flow import flow_matching_loss, sample_timesteps
from world_model.model.reference import (
    TASKS,
    ReferenceConfig,
    expand_teacher,
    reference_input,
    reference_model_config,
    task_mask,
)
from world_model.train.checkpoint import export_weights
from world_model.train.data import LatentWindows, file_digest
from world_model.train.exports import EXPORT, load_teacher
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer


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
    picks, starts, t = windows.draw(rng, batch, frames, None if clips is None else np.asarray(clips))
    x0, cond = windows.windows(picks, starts, t)
    return x0, cond, [(int(ci), int(s), t) for ci, s in zip(picks, starts, strict=True)]


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


def reference_stage(run: StageRun, rcfg: ReferenceConfig | None = None) -> dict:
    """Train (or resume) the reference model of ``run.run_dir`` (see module docstring)."""
    rcfg = rcfg or ReferenceConfig()
    cfg, tcfg = run.cfg, run.tcfg
    teacher_path = run.run_dir / "teacher" / EXPORT
    if not teacher_path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(
            f"--stage reference starts from the teacher at {teacher_path}.safetensors; run --stage teacher first"
        )
    windows = run.latents("reference")
    teacher = load_teacher(teacher_path)
    if teacher.cfg.teacher_settings() != cfg.teacher_settings():
        raise ValueError(
            f"the teacher in {teacher_path.parent} has preset {teacher.cfg.name!r}'s config, not {cfg.name!r}'s"
        )
    model = expand_teacher(teacher).train()
    ref_cfg = reference_model_config(cfg)
    meta = {"model_config": ref_cfg.to_dict(), "reference": asdict(rcfg)}
    trainer = run.trainer(model, "reference", **meta)
    counts = dict.fromkeys(TASKS, 0)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        x0, cond, extra, tasks = reference_batch(windows, tr.rng, tcfg.batch_size, rcfg)
        for task in tasks:
            counts[task] += 1
        b = x0.shape[0]
        drop = tr.rand(b) < cfg.flow.cond_drop_prob
        t = sample_timesteps((b,), cfg.flow, tr.gen)
        noise = tr.randn(*x0.shape)
        x0, extra, t, noise = tr.shard(x0), tr.shard(extra), tr.shard(t), tr.shard(noise)
        cond = tr.shard(cond).with_drop(tr.shard(drop))
        loss = flow_matching_loss(lambda xt, tt: model(torch.cat([xt, extra], dim=3), tt, cond), x0, t, noise)
        return loss, x0.shape[0] * x0.shape[1]

    summary = trainer.run(step, "reference")
    if run.place.is_main:
        export_weights(
            run.stage_dir / EXPORT,
            trainer.ema.model_state(model),
            {
                "stage": "reference",
                **meta,
                "step": trainer.step,
                "teacher_sha256": file_digest(teacher_path.with_suffix(".safetensors")),
            },
        )
    return {**summary, "task_counts": counts}
