"""Stream batched rollouts of a world model, given each step's condition arrays.

    wm = load_world_model()                                    # world_model.rollout.runtime
    conditions = RolloutConditions(wm.conditions, 8)           # the CPU side: crops, arrays
    rollouts = RolloutBatch(wm, num_rollouts=8)                # the model side
    obs0 = rollouts.start_row(0, frame, 0, conditions.restart(0, frame))  # first frame (§6)
    obs = rollouts.step_arrays([conditions.advance(i, chunk) for i, chunk in enumerate(chunks)])  # §4.2

Each rollout owns a ``torch.Generator`` seeded at its reset, and every noise tensor of that rollout
(first frame, every chunk, every re-noising) is drawn from it, so a rollout's observations do not
depend on which other rollouts share its batch: a vector env equals N single envs.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import AbstractContextManager, nullcontext
from dataclasses import fields, replace
from functools import partial
from typing import TypeVar

import numpy as np
import torch

from world_model.model.conditions import ConditionArrays, Conditions
from world_model.model.rows import split_rows
from world_model.model.tokens import ControlTokens
from world_model.observation import ALL_SENSORS, Observation, SensorSelection
from world_model.raster.classes import CLASS_PLANE, NO_LABEL
from world_model.rollout.runtime import WorldModel
from world_model.rollout.timing import StageTimer, timed
from world_model.scene import SceneFrame
from world_model.student.engine import StreamingEngine

T = TypeVar("T")


def start_key(arrays: ConditionArrays, seed: int, frame: SceneFrame) -> bytes:
    """A digest of a rollout's first-frame condition arrays, seed and the categories of the frame's
    objects (a completion adapter redraws a frame by those): rollouts with equal keys start from
    the same first frame."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(int(seed).to_bytes(8, "little", signed=True))
    digest.update(",".join(sorted(o.category for o in frame.objects)).encode())
    for f in fields(arrays):
        value = np.ascontiguousarray(getattr(arrays, f.name))
        digest.update(f"{f.name}:{value.dtype}:{value.shape}".encode())
        digest.update(value.tobytes())
    return digest.digest()


def same_torch_threads() -> None:
    """A thread pool's initializer: the thread runs torch's CPU kernels on the process's thread
    count from its first op. A new thread starts from OpenMP's default, a thread per core, until
    one of torch's ops sets it: its first small GEMM would split over the cores, and round
    otherwise than the same product on another thread."""
    torch.set_num_threads(torch.get_num_threads())


def check_starts(rows: Sequence[int], frames: Sequence[SceneFrame], seeds: Sequence[int], arrays: Sequence) -> None:
    """A ``start_rows`` call's arguments: distinct rows, one frame, seed and arrays per row."""
    if not len(rows) == len(frames) == len(seeds) == len(arrays) or len(set(rows)) != len(rows):
        raise ValueError(f"need distinct rows and one frame, seed and arrays per row, got rows {list(rows)}")


class RolloutBatch:
    """``num_rollouts`` independent rollouts advanced together, one causal chunk per step, from the
    condition arrays a :class:`~world_model.rollout.conditions.RolloutConditions` builds.
    ``every_frame``: decode every frame of a step, not only its last (the arrays must carry every
    frame's label map then). ``timer``: where the time of the stages ``student`` and ``decode``
    goes (:mod:`world_model.rollout.timing`; none by default, which waits for no device).
    ``sensors``: the sensors decoded, first frames included (the others are None in every
    observation; the arrays need the label maps only of the sensors decoded). ``restart_in_place``:
    a row restarted while others run joins the batch's frame positions (default: with more than
    one rollout); a lone rollout restarts from a fresh engine instead, so that a reset with the
    same seed repeats its episode bit for bit. ``decode_beside``: decode on a second thread while
    the student writes its cache, a step's last chunk (:meth:`step_arrays`; both count to
    ``decode``) or a reset's first frames: the two are independent, so the observations are the
    same, for a core that would idle."""

    def __init__(
        self,
        wm: WorldModel,
        num_rollouts: int,
        every_frame: bool = False,
        timer: StageTimer | None = None,
        sensors: SensorSelection = ALL_SENSORS,
        restart_in_place: bool | None = None,
        decode_beside: bool = False,
    ) -> None:
        self.wm = wm
        self.n = num_rollouts
        self.restart_in_place = num_rollouts > 1 if restart_in_place is None else restart_in_place
        self._beside = ThreadPoolExecutor(1, "decode", initializer=same_torch_threads) if decode_beside else None
        self.every_frame = every_frame
        self.sensors = sensors
        self.timer = timer
        self.engine = StreamingEngine(wm.student, wm.student_cfg, generator=self._noise)
        self.gens: list[torch.Generator | None] = [None] * num_rollouts
        self.last_arrays: list[ConditionArrays | None] = [None] * num_rollouts
        self._pending: dict[int, tuple[torch.Tensor, ConditionArrays]] = {}

    @property
    def chunk_frames(self) -> int:
        return self.wm.cfg.clip.chunk_frames

    def _row_independent(self) -> AbstractContextManager:
        """Batched student calls computed row for row as a batch of one would on CPU
        (:mod:`world_model.model.rows`), so a rollout never depends on the others in its batch."""
        return split_rows(self.n) if self._on_cpu else nullcontext()

    @property
    def _device(self) -> torch.device:
        return next(self.wm.student.parameters()).device

    @property
    def _on_cpu(self) -> bool:
        return self._device.type == "cpu"

    def _noise(self, shape: Sequence[int]) -> torch.Tensor:
        """Batch noise, each row from its own rollout's (CPU) generator; the engine moves it to the
        model's device, so a seed gives the same rollout noise on every device."""
        return torch.stack([torch.randn(tuple(shape[1:]), generator=g) for g in self.gens])

    def start_row(
        self,
        row: int,
        frame: SceneFrame,
        seed: int,
        arrays: ConditionArrays,
        reference: Mapping[str, np.ndarray] | None = None,
    ) -> Observation:
        """(Re)start rollout ``row`` at ``frame``, whose condition arrays are ``arrays``
        (:meth:`RolloutConditions.restart <world_model.rollout.conditions.RolloutConditions.restart>`):
        its first frame comes from the reference model, anchored on ``reference`` images when given
        (§6), seeded with ``seed``, and seeds the student's cache."""
        self.gens[row] = torch.Generator().manual_seed(int(seed))
        cond = Conditions.collate([arrays])
        with torch.no_grad():
            latents = self.wm.first_latents(cond, frame, reference, seed=int(seed))
        return self._first_observations(latents, cond, partial(self._start, [row], latents, [arrays]))[0]

    def start_rows(
        self,
        rows: Sequence[int],
        frames: Sequence[SceneFrame],
        seeds: Sequence[int],
        arrays: Sequence[ConditionArrays],
    ) -> list[Observation]:
        """:meth:`start_row` of several rows from controls, their first frames sampled in one
        batched reference-model call (:meth:`WorldModel.batch_first_latents`); each row exactly as
        its own :meth:`start_row` would be."""
        check_starts(rows, frames, seeds, arrays)
        for row, seed in zip(rows, seeds, strict=True):
            self.gens[row] = torch.Generator().manual_seed(int(seed))
        # Rows that start from the same controls and seed (one scene and seed under several
        # policies) get the same first frame: it is sampled once and copied (on CPU bit for bit
        # what each row's own call gives; on a GPU the smaller batch may round differently).
        keys = [start_key(a, s, f) for a, s, f in zip(arrays, seeds, frames, strict=True)]
        unique = list(dict.fromkeys(keys))
        firsts = [keys.index(k) for k in unique]
        cond = Conditions.collate([arrays[i] for i in firsts])
        latents = self.wm.batch_first_latents(cond, [frames[i] for i in firsts], [int(seeds[i]) for i in firsts])
        source = [unique.index(k) for k in keys]
        start = partial(self._start, list(rows), latents[source], list(arrays))
        obs = self._first_observations(latents, cond, start)
        return [obs[j].copy() for j in source]

    def _first_observations(
        self, latents: torch.Tensor, cond: Conditions, start: Callable[[], None]
    ) -> list[Observation]:
        """The observations of first frames ``latents`` (R, 1, V, C, h, w) sampled for ``cond``,
        decoded while ``start`` seeds the student's cache with them (the two are independent:
        beside each other with ``decode_beside``)."""
        decode = partial(self.wm.decode, latents, **cond.frames(0, 1).decoder_inputs(), sensors=self.sensors)
        return [obs[0] for obs in self._beside_of(decode, start)]

    def _beside_of(self, work: Callable[[], T], other: Callable[[], None]) -> T:
        """``work()``'s result, ``other()`` done too: on two threads with ``decode_beside`` (the
        same results, for a core that would idle), else one after the other. An error of either
        reaches the caller once both have finished."""
        if self._beside is None:
            result = work()
            other()
            return result
        future = self._beside.submit(work)
        try:
            other()
        finally:
            wait([future])
        return future.result()

    def _start(self, rows: list[int], latents: torch.Tensor, arrays: list[ConditionArrays]) -> None:
        """Seed the student's cache of ``rows`` with their first frames (R, 1, V, C, h, w)."""
        for row, a in zip(rows, arrays, strict=True):
            self.last_arrays[row] = a
        if self.engine.batch_size == self.n and self.restart_in_place:
            with torch.no_grad(), split_rows(len(rows)) if self._on_cpu else nullcontext():
                self.engine.start_rows(rows, latents, Conditions.collate(arrays))
            return
        # The first start, or a single rollout: a fresh engine, so frame positions restart at 0
        # and a reset with the same seed repeats the episode bit for bit.
        for i, row in enumerate(rows):
            self._pending[row] = (latents[i : i + 1], arrays[i])
        if len(self._pending) == self.n:
            order = sorted(self._pending)
            first = torch.cat([self._pending[r][0] for r in order])
            with torch.no_grad(), self._row_independent():
                self.engine.start(first, Conditions.collate([self._pending[r][1] for r in order]))
            self._pending.clear()

    def step_arrays(self, arrays: Sequence[Sequence[ConditionArrays] | None]) -> list[list[Observation] | None]:
        """Advance every rollout whose condition arrays of the step are given
        (:meth:`RolloutConditions.advance <world_model.rollout.conditions.RolloutConditions.advance>`):
        one per causal chunk of the step, or ``None`` for an idle rollout, whose output is
        discarded. Returns each active rollout's observations of the step's last frame (of every
        frame with ``every_frame``): :meth:`decode_step` of :meth:`advance`."""
        outs, commit = self.advance(arrays, defer_last_commit=self._beside is not None)
        # The decoder's output is on the host; a cache write beside it may still be queued on the device.
        with timed(self.timer, "decode", self._device if self._beside is not None else None):
            return self._beside_of(partial(self.decode_step, arrays, outs), commit)

    def advance(
        self,
        arrays: Sequence[Sequence[ConditionArrays] | None],
        chunks: int | None = None,
        defer_last_commit: bool = False,
    ) -> tuple[list[list[torch.Tensor]], Callable[[], None]]:
        """The student's part of :meth:`step_arrays`: each rollout's latents of the step, one
        (1, chunk, V, C, h, w) tensor per chunk (an idle rollout's too, to be discarded), and what
        is left of the step's cache writes: with ``defer_last_commit`` the last chunk's, which must
        run before the next step; else nothing.
        ``chunks``: the step's chunks when every rollout here may be idle while rollouts elsewhere
        step (another group of :class:`~world_model.rollout.shards.ShardedRollouts`): the idle
        ones advance as they would in one batch with those, keeping the frame positions alike."""
        if len(arrays) != self.n:
            raise ValueError(f"need one list of condition arrays (or None) per rollout: {self.n}, got {len(arrays)}")
        if self.engine.batch_size != self.n:
            missing = [i for i in range(self.n) if i not in self._pending]
            raise RuntimeError(f"rollouts {missing} were never reset; reset every rollout before stepping")
        shapes = {tuple(a.num_frames for a in row) for row in arrays if row is not None}
        if len(shapes) > 1 or any(k != self.chunk_frames for shape in shapes for k in shape):
            raise ValueError(
                f"every rollout's step must be the same number of the model's {self.chunk_frames}-frame chunks, "
                f"got chunks of {sorted(shapes)} frames"
            )
        steps = len(next(iter(shapes), ())) if chunks is None else chunks
        if shapes and steps != len(next(iter(shapes))):
            raise ValueError(f"chunks={chunks} differs from the {len(next(iter(shapes)))} chunks the arrays give")
        outs: list[list[torch.Tensor]] = [[] for _ in range(self.n)]
        with torch.no_grad():
            for k in range(steps):
                batch = []
                for i, row in enumerate(arrays):
                    if row is not None:
                        self.last_arrays[i] = row[k]
                    # An idle row repeats its last controls: its output is thrown away.
                    arr = self.last_arrays[i]
                    batch.append(arr if arr.num_frames == self.chunk_frames else _repeat_frames(arr, self.chunk_frames))
                cond = Conditions.collate(batch)
                with timed(self.timer, "student", self._device):
                    with self._row_independent():
                        latents, tokens = self.engine.denoise(cond)
                    if k < steps - 1 or not defer_last_commit:
                        self._commit(latents, cond, tokens)
                for i in range(self.n):
                    outs[i].append(latents[i : i + 1])
        if steps and defer_last_commit:
            return outs, partial(self._commit, latents, cond, tokens)
        return outs, _nothing

    def _commit(self, latents: torch.Tensor, cond: Conditions, tokens: ControlTokens) -> None:
        """Write a denoised chunk into the student's cache (:meth:`StreamingEngine.commit`)."""
        with torch.no_grad(), self._row_independent():
            self.engine.commit(latents, cond, tokens)

    def decode_step(
        self, arrays: Sequence[Sequence[ConditionArrays] | None], outs: list[list[torch.Tensor]]
    ) -> list[list[Observation] | None]:
        """The decoder's part of :meth:`step_arrays`: the observations of the step's latents
        ``outs`` (:meth:`advance`) of each active rollout, in one decoder call; None for the idle."""
        active = [i for i, row in enumerate(arrays) if row is not None]
        results: list[list[Observation] | None] = [None] * self.n
        if active:
            lat = torch.cat([torch.cat(outs[i], dim=1) for i in active])

            def decoded(field: str) -> np.ndarray:
                """The ConditionArrays ``field`` of the frames to decode, (active rollouts, frames, ...)."""
                rows = [np.concatenate([getattr(a, field) for a in arrays[i]]) for i in active]
                return np.stack(rows if self.every_frame else [r[-1:] for r in rows])

            if not self.every_frame:
                lat = lat[:, -1:]
            labels = decoded("labels")
            draws_cameras = self.wm.vae.draws_labels and self.sensors.cameras
            if draws_cameras and (labels[..., CLASS_PLANE, 0, 0] == NO_LABEL).all(axis=-1).any():
                raise RuntimeError(
                    "a frame to decode has no label map: build each step's conditions with the rollouts' "
                    "every_frame and sensors (RolloutConditions)"
                )
            observations = self.wm.decode(
                lat,
                labels,
                style=np.stack([arrays[i][0].style for i in active]),
                nearness=decoded("lidar_nearness"),
                sensors=self.sensors,
                range_nearness=decoded("range_nearness"),
                precipitation=decoded("precipitation"),
                precipitation_rgb=decoded("precipitation_rgb"),
            )
            for i, obs in zip(active, observations, strict=True):
                results[i] = obs
        return results


def _nothing() -> None:
    """No cache write pending."""


def _repeat_frames(arrays: ConditionArrays, frames: int) -> ConditionArrays:
    """The last frame of ``arrays`` repeated ``frames`` times (controls of an idle rollout)."""
    last = arrays.frames(arrays.num_frames - 1, arrays.num_frames)
    return replace(last, **{k: np.repeat(getattr(last, k), frames, axis=0) for k in ConditionArrays.TIME_FIELDS})
