"""Sensor backends: turn the traffic bridge's SceneFrames into observations.

* ``procedural``: the procedural sensor simulator (ground truth, fast, no model).
* ``world_model``: the causal student of the M4World checkpoint (added with the streaming engine).

A backend serves a *batch* of rollouts so that the vector env can make one call per step; a single
env is a batch of one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from world_model.sim import ProceduralSimulator

from world_model.observation import Observation
from world_model.scene import SceneFrame


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

    def __init__(self, with_bev: bool = False, every_frame: bool = False) -> None:
        self.sim = ProceduralSimulator()
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
