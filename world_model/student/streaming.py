"""How a bundle's student streams at inference: one config, stored with the bundle as ``streaming.json``.

The env (``gym.make(..., backend="world_model")``) and the evaluation report both start from the
bundle's file and override fields explicitly (env config keys ``model.*``, report flags), so the
report's headline row is what the env runs. Training-only settings (distillation, long tuning)
stay in :class:`~world_model.student.config.StudentConfig`.
"""

from __future__ import annotations

import numbers
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from world_model.student.config import DIFFUSION_STEPS, StudentConfig

STREAMING_FILE = "streaming.json"


@dataclass(frozen=True)
class StreamingConfig:
    """Inference settings of the causal student."""

    denoising_steps: int = 4  # evenly spaced from pure noise: 4 -> 1000, 750, 500, 250
    context_refresh: bool = True  # §4.2 latent context refresh of the previous chunk's last frame
    # With context_refresh: the denoising steps that refresh the context frame; the others attend to
    # the cache's copy. 0 = the first; negative indices count from the last (-1 = the last), clamped
    # at the first. None: every step (the paper's). The last two scored like every step on the
    # shipped checkpoint for 12 frame passes a chunk instead of 14 (docs/MODEL_CARD.md).
    refresh_steps: tuple[int, ...] | None = (-2, -1)
    # The first frames of a rollout kept in context beside the rolling window (an attention sink,
    # StreamingLLM / Deep Forcing); one frame lowers the shipped checkpoint's long-rollout errors.
    sink_frames: int = 1

    def __post_init__(self) -> None:
        n = self.denoising_steps
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
            raise ValueError(f"streaming.denoising_steps must be an integer >= 1, got {n!r}")
        if not isinstance(self.context_refresh, bool):
            raise ValueError(f"streaming.context_refresh must be true or false, got {self.context_refresh!r}")
        if self.refresh_steps is not None:
            steps = self.refresh_steps
            if isinstance(steps, str | bytes) or not all(
                isinstance(k, numbers.Integral) and not isinstance(k, bool) for k in steps
            ):
                raise ValueError(f"streaming.refresh_steps must be a list of step indices or null, got {steps!r}")
            if not steps or any(k >= n for k in steps):
                raise ValueError(
                    f"streaming.refresh_steps must be indices below {n} (the denoising steps; negative ones count "
                    f"from the last), got {list(steps)}"
                )
            object.__setattr__(self, "refresh_steps", tuple(int(k) for k in steps))
        s = self.sink_frames
        if isinstance(s, bool) or not isinstance(s, numbers.Integral) or s < 0:
            raise ValueError(f"streaming.sink_frames must be an integer >= 0, got {s!r}")

    def diffusion_steps(self) -> tuple[int, ...]:
        """The denoising steps on the 1000-step scale, from pure noise down."""
        n = self.denoising_steps
        return tuple(round(DIFFUSION_STEPS * (1 - k / n)) for k in range(n))

    def resolved_refresh_steps(self) -> tuple[int, ...] | None:
        """``refresh_steps`` as increasing non-negative indices (negative ones counted from the last,
        clamped at the first); None: every step, or no refresh at all when ``context_refresh`` is off."""
        if not self.context_refresh or self.refresh_steps is None:
            return None
        n = self.denoising_steps
        return tuple(sorted({max(n + k, 0) if k < 0 else k for k in self.refresh_steps}))

    def override(self, **changes: Any) -> StreamingConfig:
        """A copy with the fields of ``changes`` that are not None replaced."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ValueError(f"unknown streaming settings {sorted(unknown)}; allowed: {[f.name for f in fields(self)]}")
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def apply(self, student: StudentConfig) -> StudentConfig:
        """``student`` streaming as this config says (its training settings untouched)."""
        return replace(
            student,
            denoising_steps=self.diffusion_steps(),
            context_refresh=self.context_refresh,
            refresh_steps=self.resolved_refresh_steps(),
            sink_frames=int(self.sink_frames),
        )

    def to_dict(self) -> dict:
        d = asdict(self)
        if d["refresh_steps"] is not None:
            d["refresh_steps"] = list(d["refresh_steps"])
        return d

    @classmethod
    def from_dict(cls, d: Any, source: str = STREAMING_FILE) -> StreamingConfig:
        """Refuses unknown keys and bad values, naming ``source`` and the field."""
        if not isinstance(d, dict):
            raise ValueError(f"{source} must hold a JSON object, got {type(d).__name__}")
        allowed = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(allowed))
        if unknown:
            raise ValueError(f"{source}: unknown keys {unknown}; allowed: {allowed}")
        try:
            return cls(**d)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from e
