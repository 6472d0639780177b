"""Report rows backed by a world model: each regenerates an evaluation clip under its recorded controls.

A row streams the clip with the causal student exactly as the env does (first frame from the
reference-conditioned model, then one causal chunk at a time with the KV cache) and returns every
frame, so the report compares it frame by frame with the procedural ground truth (the Oracle).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from world_model.data.clips import Clip
from world_model.eval.report import Generated, RowFn
from world_model.model.conditions import Conditions
from world_model.model.dit import MultiViewDiT
from world_model.model.sampler import sample_latents
from world_model.runtime import RolloutBatch, WorldModel


def world_model_row(
    wm: WorldModel, seed: int = 0, anchor_first_frame: bool = False, context_refresh: bool | None = None
) -> RowFn:
    """A row generating each clip with ``wm``'s student.

    ``anchor_first_frame``: start from the clip's true first frame (all views, §6 task (a)) instead
    of sampling it from the controls. ``context_refresh`` overrides the bundle's setting (ablation).
    """
    if context_refresh is not None:
        wm = replace(wm, student_cfg=replace(wm.student_cfg, context_refresh=context_refresh))

    def row(clip: Clip) -> Generated:
        _check_resolution(wm, clip)
        frames = clip.frames
        chunk = wm.cfg.clip.chunk_frames
        rollout = RolloutBatch(wm, 1, every_frame=True)
        reference = {"cameras": np.asarray(clip.cameras[0])} if anchor_first_frame else None
        obs = [rollout.reset_row(0, frames[0], seed, reference=reference, crops=clip.crops)]
        rest = list(frames[1:])
        padded = rest + [rest[-1]] * (math.ceil(len(rest) / chunk) * chunk - len(rest)) if rest else []
        for k in range(0, len(padded), chunk):
            obs += rollout.step([padded[k : k + chunk]])[0]
        obs = obs[: len(frames)]
        return Generated(cameras=np.stack([o.cameras for o in obs]), lidar=np.stack([o.lidar for o in obs]))

    return row


def teacher_row(wm: WorldModel, teacher: MultiViewDiT, seed: int = 0, window: int | None = None) -> RowFn:
    """A row generating each clip with the bidirectional ``teacher`` (the teacher-vs-student ablation).

    The teacher has no streaming form: the clip is cut into windows of ``window`` frames (default
    its longest training length, ``clip.train_frames``), each sampled jointly from noise with the
    teacher's guided Euler sampler (``sampler.steps``), ego poses relative to the window's first
    frame as in training. Windows are independent, so motion is continuous inside a window only;
    ``wm`` supplies the VAE and the condition builder.
    """
    if teacher.cfg != wm.cfg:
        raise ValueError("the teacher and the bundle were trained with different configs")
    w = window or max(wm.cfg.clip.train_frames)

    def row(clip: Clip) -> Generated:
        _check_resolution(wm, clip)
        frames, obs = clip.frames, []
        gen = torch.Generator().manual_seed(seed)
        for start in range(0, len(frames), w):
            part = frames[start : start + w]
            cond = Conditions.collate([wm.condition_arrays(part, part[0], clip.crops)])
            obs += wm.decode(sample_latents(teacher, cond, gen))[0]
        return Generated(cameras=np.stack([o.cameras for o in obs]), lidar=np.stack([o.lidar for o in obs]))

    return row


def _check_resolution(wm: WorldModel, clip: Clip) -> None:
    h, w = wm.cfg.sensors.height, wm.cfg.sensors.width
    if clip.cameras.shape[2:4] != (h, w):
        raise ValueError(
            f"clip {clip.name} was recorded at {clip.cameras.shape[2:4]}, the model generates {(h, w)}: "
            "record the evaluation set at the model's resolution"
        )
