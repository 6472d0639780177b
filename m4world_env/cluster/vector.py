"""One Gymnasium ``VectorEnv`` over Ray actors: sub-env ``i`` of ``RayVectorEnv(N, workers=K)`` lives in
the actor whose contiguous share of ``range(N)`` holds it (:func:`~m4world_env.cluster.split_evenly`);
each actor runs a batched :class:`~m4world_env.vector.M4WorldVectorEnv` of its share, so the world
model still batches within an actor. ``reset``/``step`` send every actor its slice of the seeds and
actions at once and gather the observations in sub-env order.

Equal to the local vector env of N sub-envs: ``reset(seed=s)`` seeds sub-env ``i`` with ``s + i``
whichever actor runs it, autoreset is the same next-step autoreset (each actor's own), infos are
re-batched as the local env batches them, and a bad action is refused before any actor steps.
On the world-model backend, CPU rows are equal bit for bit at the same torch thread count: each actor
runs ``int(cpus_per_worker)`` threads (at least one), and as many groups of rollouts unless
``config.model.rollout_threads`` says otherwise (the node's other CPUs belong to other actors).
"""

from __future__ import annotations

import contextlib
import numbers
from dataclasses import replace
from typing import Any

import numpy as np
from gymnasium.error import ResetNeeded
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from m4world_env.cluster.runtime import (
    CLOSE_TIMEOUT_S,
    WORKER_START_TIMEOUT_S,
    check_capacity,
    connect,
    require_ray,
    split_evenly,
    wait_started,
)
from m4world_env.config import EnvConfig, InvalidOptionError
from m4world_env.scenario import Scenario, load_scenario
from m4world_env.traffic import ActionError
from m4world_env.traffic.bridge import TrafficBridge
from m4world_env.vector import MAX_ENVS, batched_actions, reset_seeds, split_reset_mask
from m4world_env.vector_infos import unbatch_infos

Observations = dict[str, np.ndarray]


class VectorWorker:
    """What one Ray actor holds: a batched vector env of ``num_envs`` sub-envs (its share)."""

    def __init__(
        self, num_envs: int, scenario: Scenario, backend: str, checkpoint: str | None, config: EnvConfig, threads: int
    ) -> None:
        import torch

        from m4world_env.vector import M4WorldVectorEnv

        torch.set_num_threads(threads)
        if config.model.rollout_threads is None:  # the actor's CPUs, not the node's
            config = replace(config, model=replace(config.model, rollout_threads=threads))
        self.venv = M4WorldVectorEnv(num_envs, scenario, backend, checkpoint, config=config)

    def spaces(self) -> tuple[Any, Any, dict[str, Any]]:
        return self.venv.single_observation_space, self.venv.single_action_space, self.venv.metadata

    def reset(self, seeds: list[int | None], options: dict[str, Any] | None) -> tuple[Observations, dict[str, Any]]:
        return self.venv.reset(seed=seeds, options=options)

    def step(self, actions: np.ndarray) -> tuple[Observations, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        return self.venv.step(actions)

    def close(self) -> None:
        self.venv.close()


class RayVectorEnv(VectorEnv):
    """``num_envs`` M4World sub-envs in ``workers`` Ray actors, as one vector env.

    ``address``: the Ray instance to join (:func:`~m4world_env.cluster.connect`); a process already
    connected to Ray stays on its instance. ``cpus_per_worker``: the CPUs Ray reserves for each actor
    (and its torch threads). ``scenario`` is loaded here and shipped to the actors; ``checkpoint`` must
    be a path every node can read. Workers that have not started within ``start_timeout_s`` (or
    more than the instance's CPUs hold) are a :class:`~m4world_env.cluster.ClusterError`.
    """

    # function-size: gym.make_vec's keyword arguments (the local vector env's), then the cluster's
    def __init__(
        self,
        num_envs: int = 1,
        workers: int = 1,
        scenario: Any = "highway_sunny_day",
        backend: str = "procedural",
        checkpoint: str | None = None,
        config: dict[str, Any] | EnvConfig | None = None,
        address: str | None = None,
        cpus_per_worker: float = 1.0,
        start_timeout_s: float = WORKER_START_TIMEOUT_S,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, numbers.Integral) or not 1 <= num_envs <= MAX_ENVS:
            raise InvalidOptionError(f"num_envs must be an integer in [1, {MAX_ENVS}], got {num_envs!r}")
        if isinstance(workers, bool) or not isinstance(workers, numbers.Integral) or not 1 <= workers <= num_envs:
            raise InvalidOptionError(f"workers must be an integer in [1, num_envs={num_envs}], got {workers!r}")
        if not isinstance(cpus_per_worker, numbers.Real) or cpus_per_worker <= 0:
            raise InvalidOptionError(f"cpus_per_worker must be a positive number, got {cpus_per_worker!r}")
        cfg = config if isinstance(config, EnvConfig) else EnvConfig.from_dict(config)
        scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        # The env's own action parser, to refuse a bad action before any actor steps (as the local env).
        self._actions_bridge = TrafficBridge(scenario, action_type=cfg.action_type)
        self.ray = require_ray()
        self._owns_ray = connect(address)
        self._workers, self._started = [], False
        try:
            check_capacity(self.ray, workers, cpus_per_worker)
            self.shares = split_evenly(num_envs, workers)
            actor = self.ray.remote(VectorWorker).options(num_cpus=cpus_per_worker)
            threads = max(1, int(cpus_per_worker))
            self._workers = [actor.remote(len(s), scenario, backend, checkpoint, cfg, threads) for s in self.shares]
            spaces = wait_started(self.ray, [w.spaces.remote() for w in self._workers], start_timeout_s)
            self._started = True
        except BaseException:
            self.close_extras()
            raise
        single_obs, single_act, metadata = spaces[0]
        self.num_envs = num_envs
        self.render_mode = None
        self.metadata = {**metadata, "autoreset_mode": AutoresetMode.NEXT_STEP}
        self.single_observation_space = single_obs
        self.single_action_space = single_act
        self.observation_space = batch_space(single_obs, num_envs)
        self.action_space = batch_space(single_act, num_envs)
        self._autoreset = np.zeros(num_envs, dtype=bool)
        self._observations: Observations | None = None  # the last batch: None until a reset succeeds

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Observations, dict[str, Any]]:
        seeds = reset_seeds(seed, self.num_envs)
        options, mask = split_reset_mask(options, self.num_envs)
        if mask is not None and self._observations is None:
            raise ResetNeeded(
                "reset(options={'reset_mask': ...}) restarts sub-envs of a running vector env; reset() it first"
            )
        if mask is None:
            self._observations = None  # a failed reset leaves no episode to step
            if seed is not None:
                self._np_random_seed = seeds[0]
        calls = {}
        for k, (share, worker) in enumerate(zip(self.shares, self._workers, strict=True)):
            if mask is None:
                calls[k] = worker.reset.remote(seeds[share.start : share.stop], options)
            elif mask[share.start : share.stop].any():
                share_options = {**(options or {}), "reset_mask": mask[share.start : share.stop]}
                calls[k] = worker.reset.remote(seeds[share.start : share.stop], share_options)
        results = dict(zip(calls, self.ray.get(list(calls.values())), strict=True))
        previous = self._observations
        parts = [results[k][0] if k in results else _rows(previous, s) for k, s in enumerate(self.shares)]
        infos = self._gather_infos([results[k][1] if k in results else {} for k in range(len(self.shares))])
        if mask is None:
            self._autoreset[:] = False
        else:
            self._autoreset[mask] = False
        self._observations = _concatenate(parts)
        return self._observations, infos

    def step(self, actions: Any) -> tuple[Observations, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        actions = self._check_actions(actions)
        results = self.ray.get(
            [w.step.remote(actions[s.start : s.stop]) for s, w in zip(self.shares, self._workers, strict=True)]
        )
        observations = _concatenate([r[0] for r in results])
        rewards, terminated, truncated = (np.concatenate([r[j] for r in results]) for j in (1, 2, 3))
        infos = self._gather_infos([r[4] for r in results])
        self._autoreset = terminated | truncated
        self._observations = observations
        return observations, rewards, terminated, truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        # A worker that failed to start or died has nothing left to close; workers that never
        # started (the start timed out) are killed without waiting for them.
        if self._started:
            with contextlib.suppress(self.ray.exceptions.RayError):
                self.ray.get([w.close.remote() for w in self._workers], timeout=CLOSE_TIMEOUT_S)
        for worker in self._workers:
            self.ray.kill(worker)
        self._workers = []
        if self._owns_ray:
            self.ray.shutdown()

    def _check_actions(self, actions: Any) -> np.ndarray:
        """``actions`` as one array, each sub-env's checked as its env would (ResetNeeded, ActionError)."""
        arr = batched_actions(actions, self.num_envs)
        if self._observations is None:
            raise ResetNeeded("call reset() before step() (never reset, or the last reset failed)")
        for i in np.flatnonzero(~self._autoreset):
            try:
                self._actions_bridge.parse_action(arr[i])
            except ActionError as e:
                raise type(e)(f"sub-env {i}: {e}") from e
        return arr

    def _gather_infos(self, parts: list[dict[str, Any]]) -> dict[str, Any]:
        """Each actor's batched infos re-batched under the global sub-env indices, as the local env batches."""
        infos: dict[str, Any] = {}
        for share, part in zip(self.shares, parts, strict=True):
            for i, info in zip(share, unbatch_infos(part, len(share)), strict=True):
                infos = self._add_info(infos, info, i)
        return infos


def _rows(observations: Observations | None, share: range) -> Observations:
    assert observations is not None  # a masked reset needs a running env: checked before any call
    return {k: v[share.start : share.stop] for k, v in observations.items()}


def _concatenate(parts: list[Observations]) -> Observations:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
