"""Stable-Baselines3 over a Gymnasium vector env: :class:`SB3VecEnv` presents a batched
:class:`~m4world_env.vector.M4WorldVectorEnv` or a :class:`~m4world_env.cluster.RayVectorEnv` as an SB3
``VecEnv``, with :class:`~m4world_env.wrappers.SB3Observations`' observations. Needs the ``rl`` extra.

SB3 expects a same-step reset: the observation returned with ``done`` is the next episode's first,
the last one is in ``info["terminal_observation"]``. The vector envs autoreset on the next step
(Gymnasium's default), so after a step in which episodes ended, the adapter restarts exactly those
sub-envs with ``reset(options={"reset_mask": done})``, as that next step would have: the episodes are
the vector env's own, and SB3 never sees the autoreset step.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from m4world_env.vector_infos import unbatch_infos
from m4world_env.wrappers import SB3ObservationMap


class SB3VecEnv(VecEnv):
    """``venv`` (Gymnasium ``VectorEnv``, next-step autoreset, ``reset_mask`` support) as an SB3 ``VecEnv``."""

    def __init__(self, venv: VectorEnv, lidar_sectors: int = 32) -> None:
        mode = venv.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        if mode != AutoresetMode.NEXT_STEP:
            raise ValueError(f"SB3VecEnv needs a vector env that autoresets on the next step, got {mode}")
        self.venv = venv
        self.observation_map = SB3ObservationMap(venv.single_observation_space, lidar_sectors)
        super().__init__(venv.num_envs, self.observation_map.space, venv.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> VecEnvObs:
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        options = self._options[0] or None  # one vector env: the options of its first row apply to all
        obs, infos = self.venv.reset(seed=seeds, options=options)
        self.reset_infos = unbatch_infos(infos, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return self._map(obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("SB3VecEnv.step_wait() without step_async(actions) before it")
        obs, rewards, terminated, truncated, infos = self.venv.step(self._actions)
        self._actions = None
        dones = terminated | truncated
        per_env = unbatch_infos(infos, self.num_envs)
        if dones.any():
            for i in np.flatnonzero(dones):
                per_env[i]["terminal_observation"] = self.observation_map({k: v[i] for k, v in obs.items()})
                per_env[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            obs, reset_infos = self.venv.reset(options={"reset_mask": dones})
            for i, info in enumerate(unbatch_infos(reset_infos, self.num_envs)):
                if dones[i]:
                    self.reset_infos[i] = info
        return self._map(obs), rewards.astype(np.float32), dones, per_env

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The vector env's attribute, once per index (its sub-envs are not reachable one by one)."""
        return [getattr(self.venv, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise AttributeError(f"SB3VecEnv cannot set {attr_name!r} on single sub-envs of a batched vector env")

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **kw: Any) -> list[Any]:
        raise AttributeError(f"SB3VecEnv cannot call {method_name!r} on single sub-envs of a batched vector env")

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(self._indices(indices))  # the rows of a batched env carry no per-env wrappers

    def _indices(self, indices: VecEnvIndices) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else list(indices if isinstance(indices, Iterable) else [indices])

    def _map(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        rows = [self.observation_map({k: v[i] for k, v in obs.items()}) for i in range(self.num_envs)]
        return {k: np.stack([r[k] for r in rows]) for k in rows[0]}
