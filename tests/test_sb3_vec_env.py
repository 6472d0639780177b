"""A masked reset restarts only the masked sub-envs, as autoreset would; SB3VecEnv over the batched
vector env equals SB3's DummyVecEnv of single envs; vector infos unbatch to what each sub-env gave."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from gymnasium.vector import VectorEnv

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.config import InvalidOptionError
from m4world_env.scenario import load_scenario
from m4world_env.vector_infos import unbatch_infos
from m4world_env.wrappers import SB3Observations

CONFIG = {"height": 32, "width": 56, "observation_keys": ["cameras", "lidar", "state"]}
SHORT = load_scenario("merge_cut_in").model_copy(update={"duration": 1.0})  # 5 steps an episode
ACTIONS = np.array([[0.3, 0.0], [-0.2, 0.1]], np.float32)


def _vector(n=2, scenario=SHORT):
    return gym.make_vec(
        "M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", scenario=scenario, config=CONFIG
    )


class _Batcher(VectorEnv):
    def __init__(self, n):
        self.num_envs = n


def test_unbatch_infos_inverts_gymnasium_batching():
    per_env = [
        {"time": 0.2, "crashed": True, "steps": 3, "f32": np.float32(2), "name": "a", "arr": np.ones(3), "m": {"x": 1}},
        {"time": 0.4, "crashed": False, "m": {"y": "b"}},
        {"name": "c", "steps": 5},
    ]
    batcher, infos = _Batcher(3), {}
    for i, info in enumerate(per_env):
        infos = batcher._add_info(infos, info, i)
    back = unbatch_infos(infos, 3)
    assert [set(b) for b in back] == [set(p) for p in per_env]
    again = {}
    for i, info in enumerate(back):
        again = batcher._add_info(again, info, i)
    for key in ("time", "crashed", "steps", "f32", "name", "arr", "_time", "_name"):
        assert again[key].dtype == infos[key].dtype and np.array_equal(again[key], infos[key]), key
    with pytest.raises(ValueError, match="no mask '_time'"):
        unbatch_infos({"time": np.zeros(2)}, 2)


def test_masked_reset_restarts_only_those_sub_envs_as_single_env_resets_would():
    venv = _vector()
    with pytest.raises(ResetNeeded, match="reset\\(\\) it first"):
        venv.reset(options={"reset_mask": np.array([True, False])})
    singles = [gym.make("M4World-v0", scenario=SHORT, config=CONFIG) for _ in range(2)]
    venv.reset(seed=3)
    for i, env in enumerate(singles):
        env.reset(seed=3 + i)
    for _ in range(2):
        venv.step(ACTIONS)
        for env, action in zip(singles, ACTIONS, strict=True):
            env.step(action)
    obs, infos = venv.reset(options={"reset_mask": np.array([True, False])})
    restarted, _ = singles[0].reset()
    for k in obs:
        assert np.array_equal(obs[k][0], restarted[k]), k
    assert infos["_time"].tolist() == [True, False]
    obs, rewards, *_ = venv.step(ACTIONS)  # sub-env 0 runs its new episode, sub-env 1 its first
    for i, (env, action) in enumerate(zip(singles, ACTIONS, strict=True)):
        single_obs, single_reward, *_ = env.step(action)
        assert rewards[i] == single_reward
        for k in obs:
            assert np.array_equal(obs[k][i], single_obs[k]), (i, k)
    with pytest.raises(InvalidOptionError, match="reset_mask.*shape \\(2,\\)"):
        venv.reset(options={"reset_mask": np.array([True])})
    with pytest.raises(InvalidOptionError, match="selects no sub-env"):
        venv.reset(options={"reset_mask": np.zeros(2, bool)})


def test_sb3_vec_env_equals_dummy_vec_env_of_single_envs():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.vec_env import DummyVecEnv

    from m4world_env.sb3 import SB3VecEnv

    ours = SB3VecEnv(_vector())
    theirs = DummyVecEnv(
        [lambda: SB3Observations(gym.make("M4World-v0", scenario=SHORT, config=CONFIG)) for _ in range(2)]
    )
    assert ours.observation_space == theirs.observation_space
    for venv in (ours, theirs):
        venv.seed(7)
    a, b = ours.reset(), theirs.reset()
    ends = np.zeros(2, int)
    for step in range(12):  # two episodes of 5 steps and a few steps of the third
        for k in a:
            assert np.array_equal(a[k], b[k]), (step, k)
        a, ra, da, ia = ours.step(ACTIONS)
        b, rb, db, ib = theirs.step(ACTIONS)
        assert np.array_equal(ra, rb) and np.array_equal(da, db), step
        for i in np.flatnonzero(da):
            ends[i] += 1
            for k, v in ia[i]["terminal_observation"].items():
                assert np.array_equal(v, ib[i]["terminal_observation"][k]), (step, k)
            assert ia[i]["TimeLimit.truncated"] == ib[i]["TimeLimit.truncated"]
            assert ia[i]["episode_metrics"] == ib[i]["episode_metrics"]
    assert (ends >= 2).all(), ends  # every row went through its same-step resets
    ours.close()
    theirs.close()
