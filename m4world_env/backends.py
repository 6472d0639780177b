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

from m4world_env.config import BACKENDS, REFRESH_ALL, EnvConfig, InvalidOptionError
from world_model.observation import Observation
from world_model.precision import resolve_device
from world_model.scene import SceneFrame
from world_model.sim import ProceduralSimulator, SimConfig
from world_model.sim.reference_crops import ReferenceCrops


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
) -> SensorBackend:
    """The backend for ``num_rollouts`` rollouts (1 for a single env, N for the vector env);
    ``every_frame``: observe every frame of a chunk, not only the newest (``rgb_array_list``)."""
    if backend == "procedural":
        if checkpoint is not None:
            raise InvalidOptionError("checkpoint is only used by backend='world_model'")
        return ProceduralBackend(with_bev=with_bev, every_frame=every_frame, num_rollouts=num_rollouts)
    if backend == "world_model":
        return WorldModelBackend(checkpoint, num_rollouts, with_bev, config, every_frame)
    raise InvalidOptionError(f"backend must be one of {BACKENDS}, got {backend!r}")


class WorldModelBackend:
    """The causal student of a checkpoint bundle (default: the shipped one) as the env's dynamics.

    ``reset`` samples the first frame through the reference-conditioned model (anchored on the
    user's images when ``options["reference"]`` is given) and seeds the student's KV cache; each
    ``step`` runs one batched causal chunk for every rollout and decodes the newest frame.
    The BEV observation, when asked for, is the map raster the model is conditioned on.
    Objects' reference crops (image descriptions) are cut from the procedural simulator's views
    by the rule the recorder uses (:class:`~world_model.sim.reference_crops.ReferenceCrops`), so
    the model sees in the env the conditions it was trained on.
    """

    def __init__(
        self, checkpoint: str | None, num_rollouts: int, with_bev: bool, config: EnvConfig, every_frame: bool = False
    ) -> None:
        from world_model.runtime import RolloutBatch, load_world_model

        mc = config.model
        try:
            device = resolve_device(mc.device)
        except ValueError as e:
            raise InvalidOptionError(f"config.model.device: {e}") from e
        if mc.threads is not None:
            import torch

            torch.set_num_threads(mc.threads)
        self.wm = load_world_model(checkpoint, device=device, dtype=mc.dtype)
        try:
            every_step = mc.refresh_steps == REFRESH_ALL
            self.streaming = self.wm.streaming.override(
                denoising_steps=mc.denoising_steps,
                context_refresh=mc.context_refresh,
                refresh_steps=None if every_step else mc.refresh_steps,
                sink_frames=mc.sink_frames,
            )
            if every_step:
                self.streaming = replace(self.streaming, refresh_steps=None)
            self.wm.student_cfg = self.streaming.apply(self.wm.student_cfg)
        except ValueError as e:  # e.g. refresh_steps beyond the denoising steps
            raise InvalidOptionError(f"config.model: {e}") from e
        if mc.compile:
            self.wm.student.compile_blocks()
        self.rollouts = RolloutBatch(self.wm, num_rollouts, every_frame=every_frame)
        self.rig = self.wm.rig
        self.with_bev = with_bev
        self._sim = ProceduralSimulator(
            config=replace(SimConfig(), cache_size=max(SimConfig().cache_size, 2 * num_rollouts))
        )
        self._crops = [ReferenceCrops(self._sim) for _ in range(num_rollouts)]

    def apply_adapters(self, names: Sequence[str]) -> list[str]:
        """Load a scenario's LoRA adapters (§5): :meth:`world_model.runtime.WorldModel.apply_adapters`."""
        return self.wm.apply_adapters(names)

    def _with_bev(self, obs: Observation, frame: SceneFrame) -> Observation:
        if self.with_bev:
            obs.bev = self.wm.condition_bev(frame)
        return obs

    def reset(self, index: int, frame: SceneFrame, options: dict | None, seed: int) -> Observation:
        reference = (options or {}).get("reference")
        crops = self._crops[index] = ReferenceCrops(self._sim)
        crops.update(frame)
        obs = self.rollouts.reset_row(
            index, frame, seed, reference=reference, crops=crops.crops, crop_since=crops.since
        )
        return self._with_bev(obs, frame)

    def reset_many(
        self, indices: Sequence[int], frames: Sequence[SceneFrame], options: dict | None, seeds: Sequence[int]
    ) -> list[Observation]:
        """First frames of several rollouts in one batched reference-model call; anchored on a
        user's ``reference`` images, one call each."""
        if (options or {}).get("reference") is not None or len(indices) == 1:
            return [self.reset(i, f, options, s) for i, f, s in zip(indices, frames, seeds, strict=True)]
        for i, frame in zip(indices, frames, strict=True):
            self._crops[i] = ReferenceCrops(self._sim)
            self._crops[i].update(frame)
        observations = self.rollouts.reset_rows(
            indices, frames, seeds, [self._crops[i].crops for i in indices], [self._crops[i].since for i in indices]
        )
        return [self._with_bev(o, f) for o, f in zip(observations, frames, strict=True)]

    def step(self, chunks: Sequence[Sequence[SceneFrame] | None]) -> list[list[Observation] | None]:
        for i, chunk in enumerate(chunks):  # crops of objects that came into view (or were inserted)
            if chunk is not None:
                for frame in chunk:
                    self._crops[i].update(frame)
                self.rollouts.crops[i], self.rollouts.crop_since[i] = self._crops[i].crops, self._crops[i].since
        outs = self.rollouts.step(chunks)
        return [  # observations are of the chunk's last len(out) frames (all of them with every_frame)
            None if out is None else [self._with_bev(o, f) for o, f in zip(out, chunk[-len(out) :], strict=True)]
            for out, chunk in zip(outs, chunks, strict=True)
        ]
