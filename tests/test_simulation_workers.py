"""config.workers: a world-model vector env's CPU side in worker processes (m4world_env.workers)
gives the in-process results bit for bit; errors, dead workers and shared memory are handled."""

import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.error import ResetNeeded

import m4world_env  # noqa: F401
from m4world_env.config import EnvConfig, InvalidOptionError
from m4world_env.env import M4WorldEnv
from m4world_env.scenario import load_scenario
from m4world_env.shared_arrays import ALIGN_BYTES, SharedArrays, plan_layout
from m4world_env.traffic import ActionError
from m4world_env.workers import SimulationWorkerError, worker_rows

from .test_env_world_model import _wm_vector, assert_rows_equal_singles

ROOT = Path(__file__).resolve().parents[1]
KEYS = ["cameras", "lidar", "bev", "state"]
ACTIONS = np.array([[0.5, 0.0], [-0.5, 0.2], [0.0, 0.0]], np.float32)


def _vector(bundle, workers: int, scenario="merge_cut_in", n: int = 3):
    return _wm_vector(scenario, bundle, {"observation_keys": KEYS, "workers": workers}, n)


def _shm_names() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob("m4w_*")}


def test_worker_rows_are_contiguous_and_balanced():
    assert worker_rows(5, 2) == [(0, 2), (2, 5)]
    assert worker_rows(64, 2) == [(0, 32), (32, 64)]
    assert worker_rows(3, 3) == [(0, 1), (1, 2), (2, 3)]


def test_shared_arrays_layout_attach_and_unlink():
    layout = plan_layout({"a": ((3, 5), np.dtype(np.float32)), "b": ((7,), np.dtype(bool))}, "x")
    assert layout.arrays["a"].offset == 0 and layout.arrays["b"].offset == ALIGN_BYTES
    before = _shm_names()
    shared = SharedArrays.create({"a": ((3, 5), np.float32), "b": ((7,), bool)})
    assert shared.name in _shm_names() - before
    other = SharedArrays.attach(shared.layout)
    other.arrays["a"][1, 2] = 4.5
    assert shared.arrays["a"][1, 2] == 4.5 and not shared.arrays["b"].any()
    other.close()
    shared.unlink()
    assert shared.name not in _shm_names()


def _run(venv, steps: int, seed: int) -> list[tuple]:
    out = [(*venv.reset(seed=seed), None, None, None)]
    for _ in range(steps):
        obs, rew, term, trunc, info = venv.step(ACTIONS)
        out.append((obs, info, rew, term, trunc))
    return out


def _run_singles(bundle, scenario, steps: int, seed: int) -> list[list[tuple]]:
    """Per step, each single env's (obs, reward, terminated, truncated, info), env ``i`` seeded
    ``seed + i`` and reset without a seed the step after its episode ended (reward 0 then)."""
    envs = [
        M4WorldEnv(scenario, backend="world_model", checkpoint=str(bundle), config={"observation_keys": KEYS})
        for _ in ACTIONS
    ]
    out = [[(*env.reset(seed=seed + i), 0.0, False, False) for i, env in enumerate(envs)]]
    out[0] = [(obs, rew, term, trunc, info) for obs, info, rew, term, trunc in out[0]]
    for _ in range(steps):
        row = []
        for i, env in enumerate(envs):
            if out[-1][i][2] or out[-1][i][3]:
                obs, info = env.reset()
                row.append((obs, 0.0, False, False, info))
            else:
                row.append(env.step(ACTIONS[i]))
        out.append(row)
    return out


def _row_info(infos: dict, i: int) -> dict:
    """Row ``i`` of Gymnasium's batched infos (nested dicts included)."""
    return {
        k: _row_info(v, i) if isinstance(v, dict) else v[i]
        for k, v in infos.items()
        if not k.startswith("_") and infos[f"_{k}"][i]
    }


def test_workers_equal_the_in_process_vector_env_and_single_envs(active_bundle):
    """K = 0, 1, 2 workers: observations, rewards, flags and infos over several autoresets are
    bit for bit the in-process run's, and equal the single envs' (observations up to the float
    rounding of a row restarted mid-batch, docs/scaling.md)."""
    torch.set_num_threads(1)  # the workers take the main process's count
    seed, steps = 3, 12
    short = load_scenario("merge_cut_in").model_copy(update={"duration": 1.0})  # 5-step episodes
    runs = {}
    for k in (0, 1, 2):
        venv = _vector(active_bundle, k, short)
        runs[k] = _run(venv, steps, seed)
        venv.close()
    assert sum(int(r[3].sum() + r[4].sum()) for r in runs[0][1:]) >= 2 * len(ACTIONS)  # every row restarted
    for k in (1, 2):
        for step, (a, b) in enumerate(zip(runs[0], runs[k], strict=True)):
            for key in KEYS:
                assert np.array_equal(a[0][key], b[0][key]), (k, step, key)
            assert repr(a[1:]) == repr(b[1:]), (k, step)  # infos, rewards, flags
    singles = _run_singles(active_bundle, short, steps, seed)
    for step, (vector, single) in enumerate(zip(runs[0], singles, strict=True)):
        assert_rows_equal_singles(vector[0], [s[0] for s in single], step)
        assert np.array_equal(vector[0]["state"], [s[0]["state"] for s in single]), step
        if step:
            assert vector[2].tolist() == [s[1] for s in single], step
            assert vector[3].tolist() == [s[2] for s in single] and vector[4].tolist() == [s[3] for s in single]
        for i, s in enumerate(single):
            assert _row_info(vector[1], i) == s[4], (step, i)


def test_worker_errors_edits_death_and_shared_memory(tiny_bundle):
    before = _shm_names()
    venv = _vector(tiny_bundle, 2)
    base = venv.unwrapped
    workers = base.simulation_workers
    (name,) = _shm_names() - before
    with pytest.raises(ResetNeeded, match="sub-env 0"):
        venv.step(ACTIONS)
    venv.reset(seed=0)
    bad = ACTIONS.copy()
    bad[2] = [5.0, 0.0]  # sub-env 2 lives in worker 1
    with pytest.raises(ActionError, match="sub-env 2"):
        venv.step(bad)
    track = base.envs[1].insert_object(
        {"id": "cone", "category": "cone", "track": {"kind": "static", "x": 15.0, "y": 0.0}}
    )
    assert track == "cone"
    with pytest.raises(AttributeError, match="simulation worker.*insert_object"):
        _ = base.envs[1].bridge
    obs, *_ = venv.step(ACTIONS)  # a refused step moved nothing; the next one runs
    assert obs["state"].shape[0] == 3
    h, w = base.single_observation_space["cameras"].shape[1:3]
    front = np.full((h, w, 3), 200, np.uint8)
    venv.reset(seed=0, options={"reference": {"FRONT": front}})  # user reference images still work
    with pytest.raises(TypeError, match="must be a dict"):
        venv.reset(seed=0, options={"reference": [front]})
    workers.processes[0].kill()
    with pytest.raises(SimulationWorkerError, match="worker 0.*exited"):
        venv.reset(seed=0)
    with pytest.raises(SimulationWorkerError, match="make a new vector env"):
        venv.step(ACTIONS)
    assert not any(p.is_alive() for p in workers.processes)
    assert name not in _shm_names()  # unlinked when the worker was found dead
    venv.close()


def test_closing_joins_the_workers_and_unlinks_shared_memory(tiny_bundle):
    before = _shm_names()
    venv = _vector(tiny_bundle, 1, n=2)
    workers = venv.unwrapped.simulation_workers
    assert len(_shm_names() - before) == 1
    venv.reset(seed=1)
    venv.close()
    assert not any(p.is_alive() for p in workers.processes)
    assert _shm_names() == before


def test_workers_option_is_checked(tiny_bundle):
    with pytest.raises(InvalidOptionError, match=r"config.workers must be an integer in \[0, 256\]"):
        EnvConfig.from_dict({"workers": -1})
    with pytest.raises(InvalidOptionError, match="exceeds num_envs=2"):
        _vector(tiny_bundle, 3, n=2)
    with pytest.raises(InvalidOptionError, match="needs backend='world_model'"):
        gym.make_vec("M4World-v0", num_envs=2, vectorization_mode="vector_entry_point", config={"workers": 1})
    with pytest.raises(InvalidOptionError, match="render_mode='rgb_array'"):
        gym.make_vec(
            "M4World-v0", num_envs=2, vectorization_mode="vector_entry_point", backend="world_model",
            checkpoint=str(tiny_bundle), render_mode="rgb_array", config={"workers": 1},
        )  # fmt: skip
    with pytest.raises(InvalidOptionError, match="a single env has none"):
        M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config={"workers": 1})


NO_MAIN_GUARD = """\
import gymnasium as gym

import m4world_env  # noqa: F401

venv = gym.make_vec(
    "M4World-v0", num_envs=1, vectorization_mode="vector_entry_point", backend="world_model",
    checkpoint={checkpoint!r}, config={{"workers": 1}},
)
print("built")
venv.close()
"""
SCRIPT_TIMEOUT_S = 150  # two processes import torch and load a tiny bundle; a hang ends here, failing


def test_a_script_without_a_main_guard_ends_with_the_hint_instead_of_hanging(tiny_bundle, tmp_path):
    """The spawned worker imports the script, which makes the vector env again: the worker refuses
    at once, and the main process, which sees it exit before it read its spec (VAE weights and all,
    more than a pipe buffers), ends the script with the hint."""
    script = tmp_path / "no_main_guard.py"
    script.write_text(NO_MAIN_GUARD.format(checkpoint=str(tiny_bundle)))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=SCRIPT_TIMEOUT_S
    )
    assert done.returncode != 0 and "built" not in done.stdout
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("m4world_env.workers.SimulationWorkerError: simulation worker 0"), done.stderr[-2000:]
    assert "exited with code 1 while starting" in last and "if __name__ == '__main__':" in last
