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
from world_model.streaming import DIFFUSION_STEPS, REFRESH_EVERY_STEP, StreamingConfig

# How the student stages roll out: Self-Forcing's 4 steps, the context refreshed at every one
# (the paper's), no attention sink.
TRAINING_STREAMING = StreamingConfig(
    denoising_steps=4, context_refresh=True, refresh_steps=REFRESH_EVERY_STEP, sink_frames=0
)
FLAT_STREAMING_KEYS = ("denoising_steps", "context_refresh", "refresh_steps", "sink_frames")


@dataclass(frozen=True)
class StudentConfig:
    """Everything the student stages and the streaming engine need beyond :class:`ModelConfig`."""

    # -- streaming --
    # How the student stages roll the student out (export_bundle writes the env's own settings,
    # StreamingConfig's defaults, beside it as the bundle's streaming.json).
    streaming: StreamingConfig = TRAINING_STREAMING
    timestep_shift: float = 1.0  # SD3 shift of the denoising steps; 1 matches the presets' FlowConfig.shift
    renoise: str = "fresh"  # "fresh" noise between steps (Self-Forcing) or "ddim" (implied noise)
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
        if not isinstance(self.streaming, StreamingConfig):
            raise ValueError(f"streaming must be a StreamingConfig, got {self.streaming!r}")
        if self.renoise not in ("fresh", "ddim"):
            raise ValueError(f"renoise must be 'fresh' or 'ddim', got {self.renoise!r}")
        if self.prefix_frames < 1 or self.long_clip_chunks < 1 or self.long_frames < 1:
            raise ValueError("prefix_frames, long_clip_chunks, long_frames must be >= 1")
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
        return self.streaming.denoising_steps

    def times(self) -> torch.Tensor:
        """(num_steps,) increasing flow times t_k at which the student is evaluated (t_0 = 0)."""
        sigma = torch.tensor(self.streaming.diffusion_steps(), dtype=torch.float64) / DIFFUSION_STEPS
        return shift_time(1.0 - sigma, self.timestep_shift).float()

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "streaming": self.streaming.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StudentConfig:
        """The config of a manifest's ``student_config`` (unknown keys ignored), its streaming given
        as ``streaming`` or as the flat fields of :data:`FLAT_STREAMING_KEYS`."""
        names = {f.name for f in dataclasses.fields(cls)} - {"streaming"}
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names}
        if "streaming" in d:
            kwargs["streaming"] = StreamingConfig.from_dict(d["streaming"], "student_config.streaming")
        elif any(k in d for k in FLAT_STREAMING_KEYS):
            kwargs["streaming"] = _flat_streaming(d)
        return cls(**kwargs)


def _flat_streaming(d: dict[str, Any]) -> StreamingConfig:
    """The streaming of a ``student_config`` that spells it as flat fields: the denoising steps as
    their diffusion-step list (evenly spaced from pure noise), refresh steps as indices or null for
    every step."""
    flat = {k: d[k] for k in FLAT_STREAMING_KEYS if k in d}
    steps = tuple(flat.pop("denoising_steps", TRAINING_STREAMING.diffusion_steps()))
    even = StreamingConfig(denoising_steps=len(steps), refresh_steps=REFRESH_EVERY_STEP) if steps else None
    if even is None or even.diffusion_steps() != steps:
        raise ValueError(
            f"student_config.denoising_steps must be evenly spaced from pure noise ({DIFFUSION_STEPS}), "
            f"such as {list(TRAINING_STREAMING.diffusion_steps())}, got {list(steps)}"
        )
    flat["denoising_steps"] = len(steps)
    return StreamingConfig.from_dict({**dataclasses.asdict(TRAINING_STREAMING), **flat}, "student_config")


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
