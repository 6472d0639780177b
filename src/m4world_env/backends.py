"""Sensor backends: turn the traffic bridge's SceneFrames into observations.

* ``procedural``: the procedural sensor simulator (ground truth, fast, no model).
* ``world_model``: the causal student of the M4World checkpoint (added with the streaming engine).

A backend serves a *batch* of rollouts so that the vector env can make one call per step; a single
env is a batch of one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Protocol

from m4world_env.config import BACKENDS, EnvConfig, InvalidOptionError
from world_model.observation import Observation
from world_model.scene import SceneFrame
from world_model.sim import ProceduralSimulator, SimConfig


class SensorBackend(Protocol):
    """What the env needs from a backend."""

    def reset(self, index: int, frame: SceneFrame, options: dict | None) -> Observation:
        """Start rollout ``index`` of the batch at ``frame``; returns its first observation."""

    def step(self, chunks: Sequence[Sequence[SceneFrame] | None]) -> list[list[Observation] | None]:
        """Advance every rollout whose chunk is given (``None`` = idle this step) by one chunk.

        Returns, per rollout, the observations of every frame of its chunk (or ``None``).
        """


class ProceduralBackend:
    """Renders with :class:`world_model.sim.ProceduralSimulator`.

    Only the last frame of each chunk is rendered unless ``every_frame`` is set (the observation is
    the state after the step; rendering intermediate frames would only cost time).
    """

    def __init__(self, with_bev: bool = False, every_frame: bool = False, num_rollouts: int = 1) -> None:
        # Each rollout has its own map (and maybe rig): keep every rollout's caches warm.
        base = SimConfig()
        self.sim = ProceduralSimulator(
            config=replace(
                base,
                cache_size=max(base.cache_size, 2 * num_rollouts),
                texture_cache_size=max(base.texture_cache_size, num_rollouts),
            )
        )
        self.with_bev = with_bev
        self.every_frame = every_frame

    def reset(self, index: int, frame: SceneFrame, options: dict | None) -> Observation:
        if options and options.get("reference") is not None:
            raise ValueError(
                "reset option 'reference' anchors the rollout on an image through the world model; "
                "use backend='world_model' (the procedural backend renders ground truth only)"
            )
        return self.sim.render(frame, with_bev=self.with_bev)

    def step(self, chunks: Sequence[Sequence[SceneFrame] | None]) -> list[list[Observation] | None]:
        out: list[list[Observation] | None] = []
        for chunk in chunks:
            if chunk is None:
                out.append(None)
                continue
            frames = chunk if self.every_frame else chunk[-1:]
            out.append([self.sim.render(f, with_bev=self.with_bev) for f in frames])
        return out


def make_backend(
    backend: str, checkpoint: str | None, num_rollouts: int, with_bev: bool, config: EnvConfig
) -> SensorBackend:
    """The backend for ``num_rollouts`` rollouts (1 for a single env, N for the vector env)."""
    if backend == "procedural":
        if checkpoint is not None:
            raise InvalidOptionError("checkpoint is only used by backend='world_model'")
        return ProceduralBackend(with_bev=with_bev, num_rollouts=num_rollouts)
    if backend == "world_model":
        raise InvalidOptionError(
            "backend='world_model' needs the causal student's streaming engine, which this version does not "
            "ship yet; use backend='procedural'"
        )
    raise InvalidOptionError(f"backend must be one of {BACKENDS}, got {backend!r}")
