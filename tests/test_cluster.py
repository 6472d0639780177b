"""Ray: RayVectorEnv equals the local vector env (procedural and world model), the harness on Ray gives
the local harness's report and table, also when a worker is killed mid-evaluation, and the SB3 example
trains over RayVectorEnv. One local Ray instance (2 CPUs) serves the whole module."""

import json
import runpy
import socket
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

ray = pytest.importorskip("ray", reason="Ray is not installed: pip install 'm4world-gym[cluster]'")

import m4world_env  # noqa: E402,F401  (registers M4World-v0)
from m4world_env.cli import main  # noqa: E402
from m4world_env.cluster import ClusterError, RayVectorEnv, connect, evaluate_on_ray  # noqa: E402
from m4world_env.config import InvalidOptionError  # noqa: E402
from m4world_env.evaluate import EvalRequest, evaluate, format_table  # noqa: E402
from m4world_env.scenario import load_scenario  # noqa: E402
from m4world_env.traffic import ActionError  # noqa: E402
from m4world_env.vector_infos import unbatch_infos  # noqa: E402

pytestmark = pytest.mark.ray

ROOT = Path(__file__).resolve().parents[1]
CONFIG = {"height": 32, "width": 56, "observation_keys": ["cameras", "lidar", "state"]}
SHORT = load_scenario("merge_cut_in").model_copy(update={"duration": 1.0})  # 5 steps an episode
ACTIONS = np.array([[0.3, 0.0], [0.0, 0.0], [-0.3, 0.1]], np.float32)
EVAL = {"episodes": 2, "seed": 3, "max_steps": 10, "config": {"height": 32, "width": 56}}


@pytest.fixture(scope="module", autouse=True)
def ray_instance():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def _local(n, **kw):
    return gym.make_vec("M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", **kw)


def _assert_same_step(ours, theirs, where):
    for k in theirs[0]:
        assert np.array_equal(ours[0][k], theirs[0][k]), (where, k)
    for a, b in zip(ours[1:-1], theirs[1:-1], strict=True):
        assert np.array_equal(a, b), where
    n = len(next(iter(theirs[0].values())))
    assert _plain(unbatch_infos(ours[-1], n)) == _plain(unbatch_infos(theirs[-1], n)), where


def _plain(infos):
    return json.dumps(infos, default=lambda v: v.tolist() if isinstance(v, np.ndarray) else float(v), sort_keys=True)


def test_ray_vector_env_equals_the_local_vector_env_through_autoreset():
    ours = RayVectorEnv(3, workers=2, scenario=SHORT, config=CONFIG)
    theirs = _local(3, scenario=SHORT, config=CONFIG)
    assert ours.shares == [range(0, 2), range(2, 3)]
    assert ours.observation_space == theirs.observation_space and ours.action_space == theirs.action_space
    assert ours.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    with pytest.raises(gym.error.ResetNeeded, match="reset"):
        ours.step(ACTIONS)
    _assert_same_step(ours.reset(seed=4), theirs.reset(seed=4), "reset")
    ended = np.zeros(3, bool)
    for step in range(8):  # every episode ends after at most 5 steps: autoreset happens on the way
        result = ours.step(ACTIONS)
        _assert_same_step(result, theirs.step(ACTIONS), step)
        ended |= result[2] | result[3]
    assert ended.all()
    with pytest.raises(ActionError, match="sub-env 2"):  # refused before any actor steps
        ours.step(np.array([[0.1, 0.0], [0.0, 0.0], [0.0, np.nan]], np.float32))
    with pytest.raises(InvalidOptionError, match="one action per sub-env"):
        ours.step(ACTIONS[:2])
    mask = np.array([False, False, True])  # a masked reset touches the second actor only
    _assert_same_step(ours.reset(options={"reset_mask": mask}), theirs.reset(options={"reset_mask": mask}), "mask")
    _assert_same_step(ours.step(ACTIONS), theirs.step(ACTIONS), "after the masked reset")
    ours.close()
    theirs.close()
    with pytest.raises(InvalidOptionError, match="workers must be an integer in \\[1, num_envs=2\\]"):
        RayVectorEnv(2, workers=3)


def test_ray_vector_env_equals_the_local_vector_env_on_the_world_model(active_bundle):
    kw = {"scenario": SHORT, "backend": "world_model", "checkpoint": str(active_bundle), "config": CONFIG}
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the actors' thread count (cpus_per_worker=1): equality holds at one count
    try:
        ours, theirs = RayVectorEnv(3, workers=2, **kw), _local(3, **kw)
        _assert_same_step(ours.reset(seed=0), theirs.reset(seed=0), "reset")
        for step in range(3):
            _assert_same_step(ours.step(ACTIONS), theirs.step(ACTIONS), step)
        ours.close()
        theirs.close()
    finally:
        torch.set_num_threads(before)


def test_eval_on_ray_reruns_a_killed_workers_episodes_and_counts_each_once():
    scenarios = ["empty_highway", "merge_cut_in"]
    local = evaluate(EvalRequest("idm", scenarios, **{**EVAL, "episodes": 3}), progress=False)  # 6 episodes
    counted, killed = [], []

    def kill_the_first_worker_done(done):
        counted.append((done.key, done.seed))
        if not killed:  # it has its next episode queued: that one is lost with it and must run elsewhere
            killed.append(done.worker)
            ray.kill(ray.get_actor(done.worker))

    on_ray = evaluate_on_ray(
        EvalRequest("idm", scenarios, **{**EVAL, "episodes": 3}),
        progress=False,
        workers=2,
        on_episode=kill_the_first_worker_done,
    )
    cluster = on_ray.pop("cluster")
    assert cluster["workers_lost"] == 1 and cluster["episodes_rerun"] >= 1, cluster
    assert len(counted) == len(set(counted)) == 6
    assert on_ray == local and format_table(on_ray) == format_table(local)


def test_eval_cli_on_ray_gives_the_local_table_and_report(capsys, tmp_path):
    args = ["eval", "--policy", "idm", "--scenarios", "empty_highway", "merge_cut_in", "--episodes", "2"]
    args += ["--max-steps", "5"]
    assert main([*args, "--out", str(tmp_path / "local.json")]) == 0
    local = capsys.readouterr().out
    assert main([*args, "--ray", "--workers", "2", "--out", str(tmp_path / "ray.json")]) == 0
    text = capsys.readouterr().out
    assert text.startswith(local.rpartition("wrote")[0])  # the same table
    assert "Ray: 2 workers, 0 lost, 0 episodes re-run" in text
    on_ray = json.loads((tmp_path / "ray.json").read_text())
    assert on_ray.pop("cluster") == {"workers": 2, "workers_lost": 0, "episodes_rerun": 0}
    assert on_ray == json.loads((tmp_path / "local.json").read_text())
    assert main([*args, "--workers", "2"]) == 2
    assert "add --ray" in capsys.readouterr().err


@pytest.mark.slow
def test_sb3_ray_example_trains_over_ray_vector_env(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["train_sb3_ray.py"])
    mod = runpy.run_path(str(ROOT / "examples" / "train_sb3_ray.py"))
    report = mod["main"](
        ["--timesteps", "64", "--num-envs", "2", "--workers", "2", "--height", "40", "--width", "72"]
        + ["--eval-episodes", "1", "--eval-max-steps", "5", "--out", str(tmp_path)]
    )
    assert report["timesteps"] >= 64 and report["overall"]["episodes"] == 1
    assert (tmp_path / "ppo_m4world.zip").exists() and (tmp_path / "eval.json").exists()


def test_more_workers_than_the_instance_holds_are_refused_before_any_starts():
    """The instance has 2 CPUs: workers that could never start are refused at once, not waited for."""
    with pytest.raises(ClusterError, match=r"workers=1000000 of 1 CPU each .* the Ray instance has 2: .* at most 2"):
        evaluate_on_ray(EvalRequest("idm", ["empty_highway"], **EVAL), workers=1_000_000)
    with pytest.raises(ClusterError, match=r"workers=3 of 1 CPU each need 3 CPUs"):
        RayVectorEnv(3, workers=3, scenario=SHORT, config=CONFIG)


def test_workers_that_do_not_start_in_time_end_with_an_error():
    """A worker imports torch before it answers: far longer than these timeouts."""
    with pytest.raises(ClusterError, match="no Ray worker started within 0.01 s"):
        evaluate_on_ray(EvalRequest("idm", ["empty_highway"], **EVAL), workers=1, start_timeout_s=0.01)
    with pytest.raises(ClusterError, match="1 of 1 Ray workers did not start within 0.01 s"):
        RayVectorEnv(2, workers=1, scenario=SHORT, config=CONFIG, start_timeout_s=0.01)


def test_an_address_where_nothing_listens_is_refused_before_ray_is_asked(monkeypatch):
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def never(**_):
        raise AssertionError("ray.init was called (it retries such an address for minutes)")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", never)
    with pytest.raises(ClusterError, match=f"no Ray instance answers at 127.0.0.1:{port}"):
        connect(f"127.0.0.1:{port}")
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
    with pytest.raises(ClusterError, match=f"no Ray instance answers at 127.0.0.1:{port}"):
        connect("auto")
