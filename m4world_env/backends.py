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

import numpy as np

from m4world_env.config import BACKENDS, STREAMING_NAMES, EnvConfig, InvalidOptionError
from world_model.model.conditions import ConditionArrays
from world_model.observation import ALL_SENSORS, Observation, SensorSelection
from world_model.precision import resolve_device
from world_model.rollout.conditions import RolloutConditions
from world_model.scene import SceneFrame
from world_model.sim import ProceduralSimulator, SimConfig
from world_model.streaming import StreamingConfigError


class SensorBackend(Protocol):
    """What the env needs from a backend."""

    def reset(self, index: int, frame: SceneFrame, options: dict | None, seed: int) -> Observation:
        """Start rollout ``index`` of the batch at ``frame`` (``seed`` seeds its sampling noise);
        returns its first observation."""

    def reset_many(
        self, indices: Sequence[int], frames: Sequence[SceneFrame], options: dict | None, seeds: Sequence[int]
    ) -> list[Observation]:
        """:meth:`reset` of several rollouts at once (each exactly as its own :meth:`reset`)."""

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

    def reset(self, index: int, frame: SceneFrame, options: dict | None, seed: int) -> Observation:
        if options and options.get("reference") is not None:
            raise ValueError(
                "reset option 'reference' anchors the rollout on an image through the world model; "
                "use backend='world_model' (the procedural backend renders ground truth only)"
            )
        return self.sim.render(frame, with_bev=self.with_bev)

    def reset_many(
        self, indices: Sequence[int], frames: Sequence[SceneFrame], options: dict | None, seeds: Sequence[int]
    ) -> list[Observation]:
        return [self.reset(i, f, options, s) for i, f, s in zip(indices, frames, seeds, strict=True)]

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
    backend: str,
    checkpoint: str | None,
    num_rollouts: int,
    with_bev: bool,
    config: EnvConfig,
    every_frame: bool = False,
    sensors: SensorSelection = ALL_SENSORS,
) -> SensorBackend:
    """The backend for ``num_rollouts`` rollouts (1 for a single env, N for the vector env);
    ``every_frame``: observe every frame of a chunk, not only the newest (``rgb_array_list``);
    ``sensors``: the sensors the world model decodes (the procedural backend renders both)."""
    if backend == "procedural":
        if checkpoint is not None:
            raise InvalidOptionError("checkpoint is only used by backend='world_model'")
        return ProceduralBackend(with_bev=with_bev, every_frame=every_frame, num_rollouts=num_rollouts)
    if backend == "world_model":
        return WorldModelBackend(checkpoint, num_rollouts, with_bev, config, every_frame, sensors)
    raise InvalidOptionError(f"backend must be one of {BACKENDS}, got {backend!r}")


class WorldModelBackend:
    """The causal student of a checkpoint bundle (default: the shipped one) as the env's dynamics.

    ``reset`` samples the first frame through the reference-conditioned model (anchored on the
    user's images when ``options["reference"]`` is given) and seeds the student's KV cache; each
    ``step`` runs one batched causal chunk for every rollout and decodes the newest frame.
    The BEV observation, when asked for, is the map raster the model is conditioned on. Only the
    ``sensors`` asked for are decoded (the others are None in the observations), and the camera
    label maps are drawn only for decoded cameras.
    The conditions come from a :class:`~world_model.rollout.conditions.RolloutConditions` (in
    process); :meth:`start_many` and :meth:`step_arrays` take them built elsewhere (simulation
    workers, :mod:`m4world_env.workers`).
    """

    def __init__(
        self,
        checkpoint: str | None,
        num_rollouts: int,
        with_bev: bool,
        config: EnvConfig,
        every_frame: bool = False,
        sensors: SensorSelection = ALL_SENSORS,
    ) -> None:
        import torch

        from world_model.rollout.batch import RolloutBatch
        from world_model.rollout.runtime import load_world_model
        from world_model.rollout.shards import ShardedRollouts, shard_count, usable_cpus

        mc = config.model
        try:
            device = resolve_device(mc.device)
        except ValueError as e:
            raise InvalidOptionError(f"config.model.device: {e}") from e
        if mc.threads is not None:
            torch.set_num_threads(mc.threads)
        self.wm = load_world_model(checkpoint, device=device, dtype=mc.dtype)
        try:
            self.streaming = self.wm.streaming.override(mc.streaming_changes(), STREAMING_NAMES)
        except StreamingConfigError as e:  # e.g. refresh_steps beyond the bundle's denoising steps
            raise InvalidOptionError(str(e)) from e
        self.wm.streaming = self.streaming  # the first frames' steps
        self.wm.student_cfg = replace(self.wm.student_cfg, streaming=self.streaming)
        if mc.compile:
            self.wm.student.compile_blocks()
        self.sensors = sensors
        requested = 1 if mc.compile else mc.rollout_threads  # compiled blocks: one thread (EnvConfig)
        cpus, threads = usable_cpus(), torch.get_num_threads()
        shards = shard_count(requested, num_rollouts, device.type, cpus, threads)
        if shards > 1:
            self.rollouts = ShardedRollouts(self.wm, num_rollouts, shards, every_frame=every_frame, sensors=sensors)
        else:  # one group (a single env): where two would fit, the spare core decodes beside the cache write
            spare = requested is None and shard_count(None, 2, device.type, cpus, threads) == 2
            self.rollouts = RolloutBatch(
                self.wm, num_rollouts, every_frame=every_frame, sensors=sensors, decode_beside=spare
            )
        self.rig = self.wm.rig
        self.model_cfg = self.wm.cfg
        self.with_bev = with_bev
        self.conditions = RolloutConditions(self.wm.conditions, num_rollouts, every_frame, sensors=sensors)

    def apply_adapters(self, names: Sequence[str]) -> list[str]:
        """Load a scenario's LoRA adapters (§5): :meth:`world_model.rollout.runtime.WorldModel.apply_adapters`."""
        return self.wm.apply_adapters(names)

    def reset(self, index: int, frame: SceneFrame, options: dict | None, seed: int) -> Observation:
        return self.reset_many([index], [frame], options, [seed])[0]

    def reset_many(
        self, indices: Sequence[int], frames: Sequence[SceneFrame], options: dict | None, seeds: Sequence[int]
    ) -> list[Observation]:
        arrays = [self.conditions.restart(i, f) for i, f in zip(indices, frames, strict=True)]
        return self.start_many(indices, frames, arrays, options, seeds)

    def start_many(
        self,
        indices: Sequence[int],
        frames: Sequence[SceneFrame],
        arrays: Sequence[ConditionArrays],
        options: dict | None,
        seeds: Sequence[int],
    ) -> list[Observation]:
        """:meth:`reset_many` given each first frame's condition arrays: the first frames of several
        rollouts in one batched reference-model call; anchored on a user's ``reference`` images, one
        call each."""
        reference = (options or {}).get("reference")
        if reference is not None or len(indices) == 1:
            observations = [
                self.rollouts.start_row(i, f, s, a, reference)
                for i, f, a, s in zip(indices, frames, arrays, seeds, strict=True)
            ]
        else:
            observations = self.rollouts.start_rows(indices, frames, seeds, arrays)
        return [self._with_bev([o], [a])[0] for o, a in zip(observations, arrays, strict=True)]

    def step(self, chunks: Sequence[Sequence[SceneFrame] | None]) -> list[list[Observation] | None]:
        arrays = [None if c is None else self.conditions.advance(i, c) for i, c in enumerate(chunks)]
        return self.step_arrays(arrays)

    def step_arrays(self, arrays: Sequence[Sequence[ConditionArrays] | None]) -> list[list[Observation] | None]:
        """:meth:`step` given each rollout's condition arrays of the step (``None``: idle)."""
        outs = self.rollouts.step_arrays(arrays)
        return [None if out is None else self._with_bev(out, a) for out, a in zip(outs, arrays, strict=True)]

    def _with_bev(self, observations: list[Observation], arrays: Sequence[ConditionArrays]) -> list[Observation]:
        """``observations`` (of the last frames of ``arrays``) with the BEV map raster they were
        conditioned on, when the env observes it."""
        if self.with_bev:
            bev = np.concatenate([a.bev for a in arrays])
            for obs, raster in zip(observations, bev[len(bev) - len(observations) :], strict=True):
                obs.bev = raster
        return observations
