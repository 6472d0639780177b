"""Batched vector env: N scenes, one backend call per step.

``gym.make_vec("M4World-v0", num_envs=N, vectorization_mode="vector_entry_point")`` builds this.
Each sub-env owns its traffic bridge; the sensor backend is shared and called once per step with
every sub-env's chunk, so the world model runs one batched forward for all N rollouts.

Autoreset: :attr:`AutoresetMode.NEXT_STEP` (Gymnasium's default): the step after an episode ends
resets that sub-env and returns its first observation with reward 0 and both flags False.
``reset(options={"reset_mask": mask})`` restarts only the masked sub-envs (Gymnasium's convention;
the others keep their episodes and observations), as autoreset would: adapters to libraries that
expect a same-step reset (:mod:`m4world_env.sb3`) use it.
Seeding: ``reset(seed=s)`` seeds sub-env ``i`` with ``s + i``, so the vector env equals N single envs
reset with those seeds (bit for bit on CPU: the batched world model computes row-independently,
:mod:`world_model.model.rows`). The sub-envs being (re)started, at ``reset`` or by autoreset,
get their first frames from one batched backend call.

``config={"workers": K}`` (world-model backend) runs the sub-envs' traffic, reference crops and
condition arrays in K worker processes beside the batched model (:mod:`m4world_env.workers`), with
the same results; sub-envs are then reached only through ``envs[i].insert_object`` /
``remove_object`` / ``edit_object``, and ``render_mode`` is refused.
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np
from gymnasium.error import ResetNeeded
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from m4world_env.backends import SensorBackend, make_backend
from m4world_env.config import EnvConfig, InvalidOptionError
from m4world_env.env import M4WorldEnv, check_render_mode, check_seed, decoded_sensors
from m4world_env.scenario import Scenario, load_scenario
from m4world_env.traffic import ActionError
from m4world_env.traffic.actions import detached
from m4world_env.workers import SimulationWorkers, SubEnvStep, WorkerSubEnvs, check_main_guard

MAX_ENVS = 4096  # sub-envs of one vector env (each holds a traffic simulation and a rollout)


def reset_seeds(seed: int | list[int | None] | None, num_envs: int) -> list[int | None]:
    """Each sub-env's seed of ``reset(seed=...)``: ``s + i`` for an int ``s``, the list's own, or
    None throughout. Anything else (a bool, a float, a string, a list of another length) is refused
    before any sub-env is touched."""
    if seed is None or (isinstance(seed, numbers.Integral) and not isinstance(seed, bool)):
        first = check_seed(seed)
        return [None if first is None else first + i for i in range(num_envs)]
    seeds = seed.tolist() if isinstance(seed, np.ndarray) else seed
    if not isinstance(seeds, list | tuple):
        raise InvalidOptionError(
            f"reset(seed=...) must be a non-negative integer s (sub-env i gets s + i), a list of {num_envs} "
            f"such integers or None (one per sub-env), or None, got {seed!r}"
        )
    if len(seeds) != num_envs:
        raise InvalidOptionError(f"reset(seed=list) needs {num_envs} seeds, got {len(seeds)}")
    return [check_seed(s, f"reset(seed=list): seed {i}") for i, s in enumerate(seeds)]


def split_reset_mask(options: dict[str, Any] | None, num_envs: int) -> tuple[dict[str, Any] | None, np.ndarray | None]:
    """``reset`` options without ``reset_mask``, and the mask: a bool array of ``num_envs`` with a True
    (``None`` when absent). The caller's dict is left as it was."""
    if not options or "reset_mask" not in options:
        return options, None
    rest = {k: v for k, v in options.items() if k != "reset_mask"}
    mask = options["reset_mask"]
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (num_envs,):
        described = f"shape {mask.shape}, dtype {mask.dtype}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise InvalidOptionError(
            f"options['reset_mask'] must be a bool numpy array of shape ({num_envs},), got {described}"
        )
    if not mask.any():
        raise InvalidOptionError("options['reset_mask'] selects no sub-env; set at least one entry True")
    return rest or None, mask


def batched_actions(actions: Any, num_envs: int) -> np.ndarray:
    """``actions`` as one array with a leading dimension of ``num_envs`` (one action per sub-env)."""
    try:
        arr = np.asarray(detached(actions))
    except ValueError as e:  # ragged nested lists
        raise InvalidOptionError(
            f"vector env expects an array of {num_envs} actions of equal shape (one per sub-env): {e}"
        ) from e
    if arr.shape[:1] != (num_envs,):
        raise InvalidOptionError(
            f"vector env expects one action per sub-env (leading dimension {num_envs}), got shape {arr.shape}"
        )
    return arr


class LocalSubEnvs:
    """The sub-envs in the vector env's process, their sensors from the shared ``backend``."""

    def __init__(self, envs: list[M4WorldEnv], backend: SensorBackend) -> None:
        self.envs, self.backend = envs, backend

    def reset(
        self, indices: list[int], seeds: list[int | None], options: dict[str, Any] | None
    ) -> list[tuple[dict[str, np.ndarray], dict[str, Any]]]:
        """Reset sub-envs ``indices``: their first frames in one backend call (one batched
        reference-model call on the world model), each as its own ``reset`` would give."""
        if not indices:
            return []
        begun = [self.envs[i].begin_reset(seed=s, options=options) for i, s in zip(indices, seeds, strict=True)]
        firsts = self.backend.reset_many(indices, [b[0] for b in begun], begun[0][1], [b[2] for b in begun])
        return [self.envs[i].finish_reset(first) for i, first in zip(indices, firsts, strict=True)]

    def step(self, actions: list[Any], restarting: np.ndarray) -> list[SubEnvStep]:
        """One step of every sub-env; those in ``restarting`` restart (autoreset) instead."""
        for i, env in enumerate(self.envs):  # all checked first: a bad action leaves every sub-env as it was
            if not restarting[i]:
                try:
                    env.check_action(actions[i])
                except (ActionError, ResetNeeded) as e:
                    raise type(e)(f"sub-env {i}: {e}") from e
        chunks = [None if restarting[i] else env.advance(actions[i]) for i, env in enumerate(self.envs)]
        observations = self.backend.step(chunks)
        indices = [i for i in range(len(self.envs)) if restarting[i]]
        restarted = dict(zip(indices, self.reset(indices, [None] * len(indices), None), strict=True))
        steps = []
        for i, env in enumerate(self.envs):
            if i in restarted:
                obs, info = restarted[i]
                steps.append(SubEnvStep(obs, 0.0, False, False, info))
            else:
                steps.append(SubEnvStep(*env.finish_step(chunks[i], observations[i])))
        return steps

    def close(self) -> None:
        for env in self.envs:
            env.close()


class M4WorldVectorEnv(VectorEnv):
    """N :class:`M4WorldEnv` sharing one batched sensor backend."""

    def __init__(
        self,
        num_envs: int = 1,
        scenario: Any = "highway_sunny_day",
        backend: str = "procedural",
        checkpoint: str | None = None,
        render_mode: str | None = None,
        config: dict[str, Any] | EnvConfig | None = None,
        **kwargs: Any,
    ) -> None:
        if kwargs:
            raise InvalidOptionError(f"unknown M4World vector env option(s) {sorted(kwargs)}")
        if isinstance(num_envs, bool) or not isinstance(num_envs, numbers.Integral) or not 1 <= num_envs <= MAX_ENVS:
            raise InvalidOptionError(f"num_envs must be an integer in [1, {MAX_ENVS}], got {num_envs!r}")
        check_render_mode(render_mode)
        cfg = config if isinstance(config, EnvConfig) else EnvConfig.from_dict(config)
        if cfg.workers:
            _check_workers(cfg.workers, num_envs, backend, render_mode)
        needs_bev = "bev" in cfg.observation_keys or render_mode is not None
        self.backend = make_backend(
            backend,
            checkpoint,
            num_rollouts=num_envs,
            with_bev=needs_bev,
            config=cfg,
            every_frame=render_mode == "rgb_array_list",
            sensors=decoded_sensors(cfg.observation_keys, render_mode),
        )
        # One scenario object for all sub-envs (loaded once); each sub-env has its own traffic.
        scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        if cfg.workers:
            # The sub-envs live in the workers; this one gives the spaces, checks the scenario against
            # the checkpoint and loads the scenario's adapters into the model. It is never stepped.
            first = M4WorldEnv(scenario, backend, checkpoint, None, cfg, shared_backend=self.backend)
            self._subenvs = WorkerSubEnvs(self.backend, scenario, cfg, num_envs, scenario.frames_per_step)
            self.envs = self._subenvs.proxies
        else:
            self.envs = [
                M4WorldEnv(
                    scenario, backend, checkpoint, render_mode, cfg, shared_backend=self.backend, backend_index=i
                )
                for i in range(num_envs)
            ]
            first = self.envs[0]
            self._subenvs = LocalSubEnvs(self.envs, self.backend)
        self._camera_names = first.camera_names
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.metadata = {**first.metadata, "autoreset_mode": AutoresetMode.NEXT_STEP}
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._autoreset = np.zeros(num_envs, dtype=bool)
        self._observations: dict[str, np.ndarray] | None = None  # the last batch, for a masked reset

    @property
    def camera_names(self) -> tuple[str, ...]:
        return self._camera_names

    @property
    def simulation_workers(self) -> SimulationWorkers | None:
        """The worker processes running the sub-envs (``config.workers`` > 0), else None."""
        return self._subenvs.workers if isinstance(self._subenvs, WorkerSubEnvs) else None

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        seeds = reset_seeds(seed, self.num_envs)
        options, mask = split_reset_mask(options, self.num_envs)
        if mask is not None:
            return self._reset_masked(mask, seeds, options)
        if seed is not None:
            self._np_random_seed = seeds[0]
        results = self._subenvs.reset(list(range(self.num_envs)), seeds, options)
        self._autoreset[:] = False
        infos: dict[str, Any] = {}
        for i, (_obs, info) in enumerate(results):
            infos = self._add_info(infos, info, i)
        self._observations = self._stack([obs for obs, _ in results])
        return self._observations, infos

    def _reset_masked(
        self, mask: np.ndarray, seeds: list[int | None], options: dict[str, Any] | None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        if self._observations is None:
            raise ResetNeeded(
                "reset(options={'reset_mask': ...}) restarts sub-envs of a running vector env; reset() it first"
            )
        indices = [int(i) for i in np.flatnonzero(mask)]
        results = self._subenvs.reset(indices, [seeds[i] for i in indices], options)
        self._autoreset[indices] = False
        observations = {k: v.copy() for k, v in self._observations.items()}
        infos: dict[str, Any] = {}
        for i, (obs, info) in zip(indices, results, strict=True):
            for k, batch in observations.items():
                batch[i] = obs[k]
            infos = self._add_info(infos, info, i)
        self._observations = observations
        return observations, infos

    def step(self, actions: Any) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        steps = self._subenvs.step(self._split_actions(actions), self._autoreset.copy())
        rewards = np.array([s.reward for s in steps], dtype=np.float64)
        terminated = np.array([s.terminated for s in steps], dtype=bool)
        truncated = np.array([s.truncated for s in steps], dtype=bool)
        infos: dict[str, Any] = {}
        for i, s in enumerate(steps):
            infos = self._add_info(infos, s.info, i)
        self._autoreset = terminated | truncated
        self._observations = self._stack([s.obs for s in steps])
        return self._observations, rewards, terminated, truncated, infos

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode is None:
            return None
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        self._subenvs.close()

    def _split_actions(self, actions: Any) -> list[Any]:
        return list(batched_actions(actions, self.num_envs))

    def _stack(self, obs_list: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        return {k: np.stack([o[k] for o in obs_list]) for k in obs_list[0]}


def _check_workers(workers: int, num_envs: int, backend: str, render_mode: str | None) -> None:
    """Refuse ``config.workers`` where it cannot apply (before the model loads)."""
    check_main_guard()
    if backend != "world_model":
        raise InvalidOptionError(
            f"config.workers={workers} needs backend='world_model': the procedural backend renders every "
            "sensor on the CPU and has no batched model to share; for it, run several processes "
            "(vectorization_mode='async') and leave workers at 0"
        )
    if render_mode is not None:
        raise InvalidOptionError(
            f"render_mode={render_mode!r} needs each sub-env's scene in the vector env's process; "
            f"config.workers={workers} keeps it in the workers: leave workers at 0 to render"
        )
    if workers > num_envs:
        raise InvalidOptionError(
            f"config.workers={workers} exceeds num_envs={num_envs}: at most one worker per sub-env"
        )
