"""A batch of rollouts split into groups that step at once on threads of one process.

    rollouts = ShardedRollouts(wm, num_rollouts=8, shards=2)   # two RolloutBatch of 4, a thread each
    obs = rollouts.step_arrays(arrays)                        # as RolloutBatch.step_arrays

On CPU the env runs torch on one intra-op thread (``config.model.threads``): torch's own threads
wait for each other by spinning, and a step collapses when other processes share the cores
(docs/performance.md). A vector env can still use every core: its rollouts are independent, so
each group of them is a :class:`~world_model.rollout.batch.RolloutBatch` of its own, and the
groups' student chunks and decodes run side by side on Python threads (torch releases the GIL in
its kernels). No thread waits for another inside an op, so a busy machine slows the groups down
as it would one thread, and every rollout computes exactly what it computes alone (the batches
are row-independent on CPU, :mod:`world_model.model.rows`): the observations are bit for bit those
of one batch, whatever the number of groups.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import TypeVar

import numpy as np

from world_model.model.conditions import ConditionArrays
from world_model.observation import ALL_SENSORS, Observation, SensorSelection
from world_model.rollout.batch import RolloutBatch, check_starts, same_torch_threads
from world_model.rollout.runtime import WorldModel
from world_model.rollout.timing import StageTimer, timed
from world_model.scene import SceneFrame

T = TypeVar("T")


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def shard_count(requested: int | None, num_rollouts: int, device_type: str, cpus: int, torch_threads: int) -> int:
    """How many groups :class:`ShardedRollouts` splits ``num_rollouts`` rollouts into: ``requested``
    (at most one group per rollout), or by default on CPU as many as the ``cpus`` hold groups of
    ``torch_threads`` threads each, and one on any other device (its kernels queue on one stream)."""
    if requested is None:
        requested = max(1, cpus // max(1, torch_threads)) if device_type == "cpu" else 1
    return max(1, min(requested, num_rollouts))


class ShardedRollouts:
    """``num_rollouts`` rollouts in ``shards`` contiguous groups (sizes differing by one at most),
    each a :class:`RolloutBatch` stepped on a thread of its own; the interface of a
    :class:`RolloutBatch` (rows numbered over all groups). ``timer`` times the stages in wall
    time: ``student`` while every group's chunk runs, then ``decode`` while every group decodes."""

    def __init__(
        self,
        wm: WorldModel,
        num_rollouts: int,
        shards: int,
        every_frame: bool = False,
        sensors: SensorSelection = ALL_SENSORS,
    ) -> None:
        if not 1 <= shards <= num_rollouts:
            raise ValueError(f"shards must be in [1, {num_rollouts}] (one rollout a group at least), got {shards}")
        self.wm = wm
        self.n = num_rollouts
        self.every_frame, self.sensors = every_frame, sensors
        bounds = np.linspace(0, num_rollouts, shards + 1).round().astype(int)
        self.groups = [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        self.parts = [
            RolloutBatch(wm, len(g), every_frame=every_frame, sensors=sensors, restart_in_place=num_rollouts > 1)
            for g in self.groups
        ]
        self.timer: StageTimer | None = None
        self._pool = ThreadPoolExecutor(shards, "rollouts", initializer=same_torch_threads)

    def close(self) -> None:
        """Stop the groups' threads (they also stop when this object is collected)."""
        self._pool.shutdown(wait=True)

    def _locate(self, row: int) -> tuple[RolloutBatch, int]:
        for part, group in zip(self.parts, self.groups, strict=True):
            if row in group:
                return part, row - group.start
        raise IndexError(f"rollout {row} out of range [0, {self.n})")

    def _each(self, calls: Sequence[Callable[[], T]]) -> list[T]:
        """Run ``calls`` on the groups' threads; returns their results once all of them finished
        (the first error raised then, so no group is still running when this returns)."""
        futures: list[Future[T]] = [self._pool.submit(call) for call in calls]
        wait(futures)
        return [f.result() for f in futures]

    def start_row(
        self,
        row: int,
        frame: SceneFrame,
        seed: int,
        arrays: ConditionArrays,
        reference: Mapping[str, np.ndarray] | None = None,
    ) -> Observation:
        """:meth:`RolloutBatch.start_row` of the group that holds ``row``."""
        part, local = self._locate(row)
        return part.start_row(local, frame, seed, arrays, reference)

    def start_rows(
        self,
        rows: Sequence[int],
        frames: Sequence[SceneFrame],
        seeds: Sequence[int],
        arrays: Sequence[ConditionArrays],
    ) -> list[Observation]:
        """:meth:`RolloutBatch.start_rows`, each group's rows at once on its thread."""
        check_starts(rows, frames, seeds, arrays)
        picks = [[k for k, row in enumerate(rows) if row in group] for group in self.groups]
        busy = [(part, group, ks) for part, group, ks in zip(self.parts, self.groups, picks, strict=True) if ks]
        results = self._each(
            [
                lambda part=part, group=group, ks=ks: part.start_rows(
                    [rows[k] - group.start for k in ks],
                    [frames[k] for k in ks],
                    [seeds[k] for k in ks],
                    [arrays[k] for k in ks],
                )
                for part, group, ks in busy
            ]
        )
        observations: list[Observation | None] = [None] * len(rows)
        for (_, _, ks), obs in zip(busy, results, strict=True):
            for k, o in zip(ks, obs, strict=True):
                observations[k] = o
        return observations  # type: ignore[return-value]  (every row is in one group)

    def step_arrays(self, arrays: Sequence[Sequence[ConditionArrays] | None]) -> list[list[Observation] | None]:
        """:meth:`RolloutBatch.step_arrays`, the groups side by side."""
        if len(arrays) != self.n:
            raise ValueError(f"need one list of condition arrays (or None) per rollout: {self.n}, got {len(arrays)}")
        mine = [[arrays[i] for i in group] for group in self.groups]
        # A group whose rollouts all idle still advances while the others step, as its rows
        # would in one batch.
        chunks = next((len(row) for row in arrays if row is not None), 0)
        device = next(self.wm.student.parameters()).device
        with timed(self.timer, "student", device):
            calls = [lambda p=p, a=a: p.advance(a, chunks)[0] for p, a in zip(self.parts, mine, strict=True)]
            outs = self._each(calls)
        with timed(self.timer, "decode"):
            decoded = self._each(
                [lambda p=p, a=a, o=o: p.decode_step(a, o) for p, a, o in zip(self.parts, mine, outs, strict=True)]
            )
        return [obs for group in decoded for obs in group]
