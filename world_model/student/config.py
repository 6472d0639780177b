"""Configuration of the causal few-step student (paper §4.2-§4.4) and its few-step schedule.

Few-step schedule. Self-Forcing/CausVid denoise a chunk at the diffusion steps
``[1000, 750, 500, 250]`` (1000 = pure noise), i.e. noise levels sigma = step / 1000, warped by
the SD3 shift ``sigma' = s sigma / (1 + (s - 1) sigma)``. Our flow convention has t = 1 for data,
so step k is the time ``t = 1 - sigma'``: with shift 1 the default list gives t = (0, 0.25, 0.5,
0.75); with Wan's shift 5 it gives (0, 0.0625, 0.167, 0.375). At each time the student predicts
the clean chunk ``x0 = x_t + (1 - t) v``; between steps the prediction is re-noised to the next
time (fresh noise, as Self-Forcing; or the noise implied by the current sample, ``"ddim"``); the
last step's x0-prediction is the output.

The rolling context window is ``ModelConfig.clip.context_frames`` (not repeated here), and a
chunk is ``clip.chunk_frames`` frames.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from world_model.model.config import ModelConfig
from world_model.model.flow import shift_time

DIFFUSION_STEPS = 1000  # the scale the step list is written in (1000 = pure noise)


@dataclass(frozen=True)
class StudentConfig:
    """Everything the student stages and the streaming engine need beyond :class:`ModelConfig`."""

    # -- streaming / inference --
    denoising_steps: tuple[int, ...] = (1000, 750, 500, 250)  # Self-Forcing's list, 1000 = noise
    timestep_shift: float = 1.0  # SD3 shift of that list; 1 matches the presets' FlowConfig.shift
    renoise: str = "fresh"  # "fresh" noise between steps (Self-Forcing) or "ddim" (implied noise)
    context_refresh: bool = True  # §4.2 latent context refresh of the previous chunk's last frame
    # Which denoising steps (indices into ``denoising_steps``) refresh the context frame; the others
    # attend to the cache's copy of it, as without refresh. None: every step (the paper's). Each
    # refresh costs a frame more per forward (refreshing at all 4 steps: ~1.4x a chunk's compute).
    refresh_steps: tuple[int, ...] | None = None
    sink_frames: int = 0  # first frames of a rollout kept in context forever (attention sink)
    prefix_frames: int = 1  # clean conditioning frames a rollout starts from (the reset frame)

    # -- Self-Forcing + DMD --
    critic_updates: int = 5  # critic steps per generator step (DMD2)
    denoise_loss_prob: float = 0.1  # probability of adding the supervised denoising loss
    dmd_min_t: float = 0.02  # DMD noise times are drawn in [dmd_min_t, dmd_max_t]: the guided
    dmd_max_t: float = 0.98  # score is undefined at t = 1 and uninformative at t = 0
    # Guidance scale of the DMD real score (camera CFG and LiDAR APG alike); None keeps the teacher's
    # sampler scales. DMD's reverse KL seeks modes, and guidance sharpens the modes it seeks.
    dmd_guidance_scale: float | None = None

    # -- long-video tuning (LongLive) --
    long_frames: int = 600  # length of one self-rollout before it restarts from data
    long_clip_chunks: int = 2  # chunks of each newly generated clip trained with DMD
    # Chunks the rollout advances without training (no critic update, no gradient) after each
    # trained clip: 0 trains every clip (LongLive). A tuning run of a few dozen steps otherwise only
    # ever sees a rollout's first frames (20 steps x 2 chunks x 2 frames = 80 of 600), never the
    # late frames where the drift it should correct happens.
    long_skip_chunks: int = 0

    def __post_init__(self) -> None:
        steps = self.denoising_steps
        if (
            not steps
            or any(not 0 < s <= DIFFUSION_STEPS for s in steps)
            or any(a <= b for a, b in zip(steps, steps[1:], strict=False))
        ):
            raise ValueError(f"denoising_steps must be decreasing values in (0, {DIFFUSION_STEPS}], got {steps}")
        if steps[0] != DIFFUSION_STEPS:
            raise ValueError(f"denoising_steps must start at pure noise ({DIFFUSION_STEPS}), got {steps}")
        if self.refresh_steps is not None:
            idx = tuple(self.refresh_steps)
            object.__setattr__(self, "refresh_steps", idx)  # a list from a caller: hashable like the rest
            integral = all(isinstance(k, int) and not isinstance(k, bool) for k in idx)
            if not integral or not idx or sorted(set(idx)) != list(idx) or not 0 <= idx[0] <= idx[-1] < len(steps):
                raise ValueError(
                    f"refresh_steps must be increasing step indices in [0, {len(steps) - 1}] (one per "
                    f"denoising step to refresh at), or None for every step; got {idx}"
                )
            if not self.context_refresh:
                raise ValueError("refresh_steps needs context_refresh=True (it says at which steps to refresh)")
        if self.renoise not in ("fresh", "ddim"):
            raise ValueError(f"renoise must be 'fresh' or 'ddim', got {self.renoise!r}")
        if self.prefix_frames < 1 or self.sink_frames < 0 or self.long_clip_chunks < 1 or self.long_frames < 1:
            raise ValueError("prefix_frames, long_clip_chunks, long_frames must be >= 1 and sink_frames >= 0")
        if self.long_skip_chunks < 0:
            raise ValueError(f"long_skip_chunks must be >= 0, got {self.long_skip_chunks}")
        if not 0.0 <= self.denoise_loss_prob <= 1.0:
            raise ValueError(f"denoise_loss_prob must be in [0, 1], got {self.denoise_loss_prob}")
        if self.dmd_guidance_scale is not None and not self.dmd_guidance_scale > 0.0:
            raise ValueError(f"dmd_guidance_scale must be > 0 (1 = no guidance), got {self.dmd_guidance_scale}")
        if not 0.0 < self.dmd_min_t < self.dmd_max_t < 1.0:
            raise ValueError(f"need 0 < dmd_min_t < dmd_max_t < 1, got {self.dmd_min_t}, {self.dmd_max_t}")

    @property
    def num_steps(self) -> int:
        return len(self.denoising_steps)

    def times(self) -> torch.Tensor:
        """(num_steps,) increasing flow times t_k at which the student is evaluated (t_0 = 0)."""
        sigma = torch.tensor(self.denoising_steps, dtype=torch.float64) / DIFFUSION_STEPS
        return shift_time(1.0 - sigma, self.timestep_shift).float()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StudentConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names})


def rollout_blocks(start: int, frames: int, prefix_frames: int, chunk_frames: int) -> torch.Tensor:
    """(frames,) causal block index of rollout frames ``start .. start + frames - 1``.

    A rollout is ``prefix_frames`` conditioning frames (block 0), then chunks of ``chunk_frames``.
    """
    f = torch.arange(start, start + frames)
    return torch.where(f < prefix_frames, 0, 1 + (f - prefix_frames).clamp_min(0) // chunk_frames)


def check_student(cfg: ModelConfig, scfg: StudentConfig) -> None:
    """Raise when the student's layout does not fit the model's clip layout."""
    if scfg.prefix_frames > cfg.clip.context_frames:
        raise ValueError(f"prefix_frames {scfg.prefix_frames} exceeds the context window {cfg.clip.context_frames}")
