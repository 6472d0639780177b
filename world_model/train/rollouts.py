"""Long self-rollouts on recorded clips: a rollout longer than its clip plays the clip back and
forth (reflected), which keeps consecutive frames physically adjacent; its controls and first
latents are gathered from :class:`~world_model.train.data.LatentWindows`."""

from __future__ import annotations

import numpy as np
import torch

from world_model.model.conditions import Conditions
from world_model.train.data import LatentWindows


def reflected_index(i: int | np.ndarray, length: int | np.ndarray) -> int | np.ndarray:
    """Frame i of a clip of ``length`` frames played back and forth: 0 1 .. n-1 n-2 .. 0 1 ..
    (element-wise on arrays)."""
    i, length = np.asarray(i), np.asarray(length)
    period = np.maximum(2 * length - 2, 1)
    m = i % period
    out = np.where(length == 1, 0, np.where(m < length, m, 2 * length - 2 - m))
    return int(out) if out.ndim == 0 else out


def rollout_batch(
    windows: LatentWindows, clips: list[int], start: int, frames: int, anchor: int
) -> tuple[torch.Tensor, Conditions]:
    """Latents (B, frames, ...) and conditions of rollout frames [start, start + frames) per row
    (row b plays clip ``clips[b]``), ego relative to rollout frame ``anchor``."""
    clips_arr = np.asarray(clips, dtype=np.int64)
    lengths = windows.lengths[clips_arr][:, None]
    index = reflected_index(np.arange(start, start + frames)[None, :], lengths)
    return windows.gather(clips_arr, index, reflected_index(np.full(len(clips), anchor), lengths[:, 0]))


def rollout_conditions(windows: LatentWindows, clips: list[int], start: int, frames: int, anchor: int) -> Conditions:
    """The conditions of :func:`rollout_batch`."""
    return rollout_batch(windows, clips, start, frames, anchor)[1]


def rollout_starts(
    windows: LatentWindows, rng: np.random.Generator, batch: int, prefix: int
) -> tuple[list[int], torch.Tensor, Conditions]:
    """A fresh long rollout per row: random clips, their first ``prefix`` latents (B, prefix, ...)
    and those frames' conditions (ego relative to rollout frame 0)."""
    clips = [int(i) for i in rng.integers(len(windows.clips), size=batch)]
    first, cond = rollout_batch(windows, clips, 0, prefix, 0)
    return clips, first, cond
