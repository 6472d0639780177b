"""A vector env's rollouts stepped in groups on threads (world_model.rollout.shards): the same
observations bit for bit as one batch, whatever the number of groups; the count, its bounds and
its errors."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env.config import EnvConfig, InvalidOptionError
from world_model.rollout.batch import RolloutBatch
from world_model.rollout.runtime import load_world_model
from world_model.rollout.shards import ShardedRollouts, shard_count
from world_model.rollout.timing import StageTimer

KEYS = {"observation_keys": ["cameras", "lidar", "state"]}
ACTIONS = np.array([[0.3, 0.0], [0.0, 0.0], [-0.3, 0.0]], np.float32)


@pytest.mark.parametrize(
    "requested, rollouts, device, cpus, threads, expected",
    [
        (None, 8, "cpu", 2, 1, 2),  # a group per core
        (None, 8, "cpu", 16, 4, 4),  # groups of 4 torch threads
        (None, 8, "cpu", 2, 2, 1),  # torch's threads take the cores already
        (None, 3, "cpu", 16, 1, 3),  # at most a group per rollout
        (None, 1, "cpu", 16, 1, 1),  # a single env
        (None, 8, "cuda", 16, 1, 1),  # one stream
        (4, 8, "cpu", 2, 1, 4),  # asked for: more groups than cores
        (4, 2, "cpu", 2, 1, 2),
        (1, 8, "cpu", 16, 1, 1),
        (2, 8, "cuda", 16, 1, 2),
    ],
)
def test_shard_count(requested, rollouts, device, cpus, threads, expected):
    assert shard_count(requested, rollouts, device, cpus, threads) == expected


def test_compile_steps_on_one_thread():
    with pytest.raises(InvalidOptionError, match=r"rollout_threads=2 needs config\.model\.compile off"):
        EnvConfig.from_dict({"model": {"compile": True, "rollout_threads": 2}})
    EnvConfig.from_dict({"model": {"compile": True, "rollout_threads": 1}})


@pytest.fixture
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_group_threads_run_torch_on_the_process_thread_count(tiny_bundle, one_thread):
    """A fresh thread's first small GEMM would use OpenMP's default thread count (a thread per
    core) and round differently from the main thread's; the groups' and the decoder's threads
    start on the process's count."""
    gen = torch.Generator().manual_seed(0)
    x, w = torch.randn(6, 256, generator=gen), torch.randn(128, 256, generator=gen)
    main = torch.nn.functional.linear(x, w)
    wm = load_world_model(tiny_bundle, dtype="float32")
    rollouts = ShardedRollouts(wm, 2, 2)
    beside = RolloutBatch(wm, 1, decode_beside=True)
    try:
        for pool in (rollouts._pool, beside._beside):
            firsts = [pool.submit(torch.nn.functional.linear, x, w).result() for _ in range(2)]
            assert all(torch.equal(first, main) for first in firsts)
    finally:
        rollouts.close()
        beside._beside.shutdown()


def _episode(bundle, rollout_threads: int) -> tuple[list, type]:
    """Observations, rewards and flags of a 3-env vector env over a reset, 6 steps, a reset of sub-env
    1 alone (one group's row) and 24 more steps, in which sub-env 0 leaves the road and restarts
    (its step idle, so with 3 groups one group idles while the others step)."""
    cfg = {**KEYS, "model": {"rollout_threads": rollout_threads}}
    venv = gym.make_vec(
        "M4World-v0", num_envs=3, vectorization_mode="vector_entry_point", scenario="merge_cut_in",
        backend="world_model", checkpoint=str(bundle), config=cfg,
    )  # fmt: skip
    try:
        kind = type(venv.unwrapped.backend.rollouts)
        out = [venv.reset(seed=7)[0]]
        for t in range(30):
            if t == 6:
                mask = np.array([False, True, False])
                out.append(venv.reset(seed=[None, 21, None], options={"reset_mask": mask})[0])
            out.append(venv.step(ACTIONS)[:4])
        return out, kind
    finally:
        venv.close()


def test_groups_observe_what_one_batch_observes(active_bundle, one_thread):
    one, kind = _episode(active_bundle, 1)
    assert kind is RolloutBatch
    assert any(step[2][0] for step in one[1:] if not isinstance(step, dict))  # sub-env 0 terminated
    for groups in (2, 3):
        got, kind = _episode(active_bundle, groups)
        assert kind is ShardedRollouts
        for step, (a, b) in enumerate(zip(one, got, strict=True)):
            obs_a, obs_b = (a, b) if isinstance(a, dict) else (a[0], b[0])
            for key in obs_a:
                assert np.array_equal(obs_a[key], obs_b[key]), f"{groups} groups, step {step}, {key}"
            if not isinstance(a, dict):
                for x, y in zip(a[1:], b[1:], strict=True):
                    assert np.array_equal(x, y), f"{groups} groups, step {step}"


def test_groups_split_the_rows_and_report_errors(tiny_bundle, one_thread):
    wm = load_world_model(tiny_bundle, dtype="float32")
    with pytest.raises(ValueError, match=r"shards must be in \[1, 2\]"):
        ShardedRollouts(wm, 2, 3)
    rollouts = ShardedRollouts(wm, 5, 2)
    try:
        assert [list(g) for g in rollouts.groups] == [[0, 1], [2, 3, 4]]
        assert [p.n for p in rollouts.parts] == [2, 3]
        with pytest.raises(ValueError, match="one list of condition arrays"):
            rollouts.step_arrays([None] * 4)
        with pytest.raises(RuntimeError, match="never reset"):  # a group's error, raised here
            rollouts.step_arrays([None] * 5)
        with pytest.raises(IndexError, match=r"rollout 5 out of range"):
            rollouts.start_row(5, None, 0, None)
    finally:
        rollouts.close()


def test_stage_times_are_wall_times_of_the_groups_together(active_bundle, one_thread):
    venv = gym.make_vec(
        "M4World-v0", num_envs=2, vectorization_mode="vector_entry_point", scenario="merge_cut_in",
        backend="world_model", checkpoint=str(active_bundle), config={**KEYS, "model": {"rollout_threads": 2}},
    )  # fmt: skip
    try:
        venv.reset(seed=3)
        timer = venv.unwrapped.backend.rollouts.timer = StageTimer()
        venv.step(ACTIONS[:2])
        assert timer.seconds["student"] > 0 and timer.seconds["decode"] > 0
    finally:
        venv.close()


def _single_episode(bundle, rollout_threads: int | None) -> tuple[list, bool]:
    env = gym.make(
        "M4World-v0", scenario="merge_cut_in", backend="world_model", checkpoint=str(bundle),
        config={**KEYS, "model": {"rollout_threads": rollout_threads}},
    )  # fmt: skip
    beside = env.unwrapped.backend.rollouts._beside is not None
    out = [env.reset(seed=4)[0]]
    out += [env.step(ACTIONS[0])[0] for _ in range(8)]
    out.append(env.reset(seed=5)[0])
    out += [env.step(ACTIONS[2])[0] for _ in range(3)]
    env.close()
    return out, beside


def test_a_single_env_decodes_beside_the_cache_writes_and_observes_the_same(active_bundle, one_thread, monkeypatch):
    monkeypatch.setattr("world_model.rollout.shards.usable_cpus", lambda: 2)
    beside, on = _single_episode(active_bundle, None)
    plain, off = _single_episode(active_bundle, 1)  # one thread asked for: nothing beside
    assert on and not off
    for step, (a, b) in enumerate(zip(beside, plain, strict=True)):
        for key in a:
            assert np.array_equal(a[key], b[key]), f"step {step}, {key}"


def test_a_decode_error_beside_the_cache_write_reaches_the_caller(active_bundle, one_thread, monkeypatch):
    monkeypatch.setattr("world_model.rollout.shards.usable_cpus", lambda: 2)
    env = gym.make("M4World-v0", scenario="merge_cut_in", backend="world_model", checkpoint=str(active_bundle))
    env.reset(seed=0)
    rollouts = env.unwrapped.backend.rollouts
    position = rollouts.engine.position

    def broken(*args):
        raise RuntimeError("decoder broke")

    monkeypatch.setattr(rollouts, "decode_step", broken)
    with pytest.raises(RuntimeError, match="decoder broke"):
        env.step(ACTIONS[0])
    assert rollouts.engine.position > position  # the cache write finished all the same
    env.close()


def test_a_first_frame_decode_error_beside_the_cache_seed_reaches_the_caller(active_bundle, one_thread, monkeypatch):
    monkeypatch.setattr("world_model.rollout.shards.usable_cpus", lambda: 2)
    env = gym.make("M4World-v0", scenario="merge_cut_in", backend="world_model", checkpoint=str(active_bundle))
    rollouts = env.unwrapped.backend.rollouts
    assert rollouts._beside is not None and rollouts.engine.cache is None

    def broken(*args, **kwargs):
        raise RuntimeError("decoder broke")

    monkeypatch.setattr(rollouts.wm, "decode", broken)
    with pytest.raises(RuntimeError, match="decoder broke"):
        env.reset(seed=0)
    assert rollouts.engine.cache is not None  # the first frame seeded the cache all the same
    env.close()
