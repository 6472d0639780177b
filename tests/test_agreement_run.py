"""The agreement run: the zoo on both backends, cell by cell, resumable, each row the episode
`m4world eval` runs; and the first frame shared by rows that start alike."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

import m4world_env.agreement.run as agreement_run
from m4world_env.agreement.run import AgreementPlan, cells, run_agreement
from m4world_env.cli import main
from m4world_env.evaluate import EvalRequest, evaluate
from m4world_env.vector import M4WorldVectorEnv

POLICIES = ("gap_keeper", "gap_keeper_blind_front_lidar", "cruise_lane_keeper")


def plan(bundle, steps: int = 3) -> AgreementPlan:
    return AgreementPlan(
        policies=POLICIES, scenarios=("highway_dense_rain_dusk",), seeds=(1,), steps=steps, checkpoint=str(bundle)
    )


@pytest.fixture(scope="module")
def finished_run(active_bundle, tmp_path_factory):
    out = tmp_path_factory.mktemp("agreement")
    return out, run_agreement(plan(active_bundle), out, videos=1, progress=False)


def test_a_run_writes_its_report_summary_plot_and_videos(finished_run):
    out, summary = finished_run
    assert sorted(summary["policies"]) == sorted(POLICIES)
    assert summary["agreement"]["episodes"] == len(POLICIES)
    assert json.loads((out / "summary.json").read_text()) == summary
    assert "Agreement over the zoo" in (out / "report.md").read_text()
    assert (out / "scatter.png").stat().st_size > 10_000
    (key, video), *_ = summary["videos"].items()
    assert key == summary["disagreements"][0]["key"] and (out / video).stat().st_size > 1_000
    progress = json.loads((out / "progress.json").read_text())
    assert progress["cells_done"] == progress["cells"] == 2 and progress["running"] == []
    assert not list((out / "running").glob("*.json"))  # each cell's step file goes with the cell


def test_each_row_is_the_episode_m4world_eval_runs(finished_run, active_bundle):
    out, _ = finished_run
    for backend in ("procedural", "world_model"):
        cell = json.loads((out / "episodes" / backend / "highway_dense_rain_dusk" / "seed1.json").read_text())
        for record in cell["records"]:
            checkpoint = str(active_bundle) if backend == "world_model" else None
            alone = evaluate(
                EvalRequest(
                    record["policy"],
                    ["highway_dense_rain_dusk"],
                    seed=1,
                    backend=backend,
                    checkpoint=checkpoint,
                    max_steps=3,
                ),
                progress=False,
            )["episodes"][0]
            for k in ("pdms", "collision", "progress", "distance_m", "comfort", "min_ttc_s"):
                assert record[k] == alone[k], (backend, record["policy"], k)


def test_a_stopped_run_resumes_the_cells_it_had_not_finished(finished_run, active_bundle, monkeypatch, tmp_path):
    out, summary = finished_run
    resumed = tmp_path / "resumed"
    for f in (out / "episodes").rglob("*.json"):
        target = resumed / f.relative_to(out)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(f.read_text())
    (resumed / "episodes" / "world_model" / "highway_dense_rain_dusk" / "seed1.json").unlink()
    ran = []
    real = agreement_run.run_cell
    monkeypatch.setattr(
        agreement_run,
        "run_cell",
        lambda cell, p, on_step=None, rollout_threads=None: ran.append(cell) or real(cell, p, on_step, rollout_threads),
    )
    again = run_agreement(plan(active_bundle), resumed, videos=0, progress=False)
    assert [c.backend for c in ran] == ["world_model"]
    assert again["policies"] == summary["policies"] and again["agreement"] == summary["agreement"]


def test_a_run_refuses_to_resume_with_other_settings(finished_run, active_bundle):
    out, _ = finished_run
    with pytest.raises(ValueError, match="steps"):
        run_agreement(plan(active_bundle, steps=4), out, videos=0, progress=False)


def test_plans_name_every_cell_and_refuse_what_cannot_run():
    p = AgreementPlan(policies=("gap_keeper", "bc_lidar_small"), scenarios=("s", "t"), seeds=(0, 1), steps=2)
    assert len(cells(p)) == 8
    fingerprint = p.to_json()
    assert fingerprint["checkpoint"] == "shipped" and fingerprint["citations"] == ["gap_keeper@v1", "bc_lidar_small@v1"]
    assert list(fingerprint["member_files"]) == ["bc_lidar_small"]  # its weights' digest: retrained weights differ
    for flag, kwargs in (
        ("--policies", {"policies": ("a", "a")}),
        ("--scenarios", {"scenarios": ("s", "s")}),
        ("--seeds", {"seeds": (1, 1)}),
        ("--scenarios", {"scenarios": ("my/road.yaml",)}),
        ("--steps", {"steps": 0}),
        ("--truth-noise", {"truth_noise": 0.0}),
        ("--truth-noise", {"truth_noise": float("nan")}),
        ("--truth-noise", {"truth_noise": 65.0}),
        ("--truth-noise", {"truth_noise": True}),
        ("--dtype", {"dtype": "float16"}),
    ):
        with pytest.raises(ValueError, match=flag):
            AgreementPlan(**{"policies": ("a",), "scenarios": ("s",), "seeds": (0,), "steps": 2, **kwargs})


@pytest.mark.parametrize(
    "args, message",
    [
        (["--policies", "nobody"], "unknown zoo policy"),
        (["--scenarios", "no_such_road"], "no_such_road"),
        (["--checkpoint", "/no/such/bundle"], "no bundle"),
        (["--truth-noise", "-1"], "--truth-noise"),
        (["--truth-noise", "2", "--videos", "1"], "--videos 0"),
    ],
)
def test_the_command_refuses_bad_options_before_any_work(args, message, tmp_path, capsys):
    assert main(["agreement", "--out", str(tmp_path / "run"), *args]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run" / "episodes").exists()


def test_the_noisy_ground_truth_takes_the_world_models_place_seen_through_camera_noise(tmp_path, monkeypatch):
    """The floor: the 'world_model' cells drive the ground truth, each policy seeing its cameras
    through the noise (its LiDAR as it is); the cells are what the plan says, run after run."""
    noisy = AgreementPlan(
        policies=POLICIES, scenarios=("highway_dense_rain_dusk",), seeds=(1,), steps=3, truth_noise=2.0
    )
    assert noisy.to_json()["truth_noise"] == 2.0 and "truth_noise" not in replace(noisy, truth_noise=None).to_json()
    seen = []
    real = agreement_run.noisy_cameras
    spy = lambda obs, sigma, rng: seen.append((obs, real(obs, sigma, rng))) or seen[-1][1]  # noqa: E731
    monkeypatch.setattr(agreement_run, "noisy_cameras", spy)
    summary = run_agreement(noisy, tmp_path / "floor", progress=False)
    assert summary["checkpoint"].startswith("the ground truth") and "videos" not in summary
    assert len(seen) >= len(POLICIES)  # the first frame and each step's, per row
    for raw, through in seen:
        assert np.array_equal(through["lidar"], raw["lidar"]) and through["cameras"].dtype == np.uint8
        diff = through["cameras"].astype(np.float32) - raw["cameras"]
        assert 1.0 < float(diff.std()) < 3.0
    again = run_agreement(noisy, tmp_path / "again", progress=False)
    assert again["agreement"] == summary["agreement"] and again["policies"] == summary["policies"]


def test_a_run_in_another_precision_runs_its_world_model_in_it_and_says_so(active_bundle, tmp_path, monkeypatch):
    built = []
    real = M4WorldVectorEnv.__init__
    monkeypatch.setattr(M4WorldVectorEnv, "__init__", lambda self, *a, **kw: built.append(kw) or real(self, *a, **kw))
    fp32 = replace(plan(active_bundle, steps=2), policies=("gap_keeper",), dtype="float32")
    summary = run_agreement(fp32, tmp_path / "fp32", videos=0, progress=False)
    assert [kw["config"]["model"]["dtype"] for kw in built] == ["float32", "float32"]  # both cells
    assert summary["checkpoint"] == f"{active_bundle.resolve()} (float32)"
    assert fp32.to_json()["dtype"] == "float32" and "dtype" not in replace(fp32, dtype="auto").to_json()


def test_noisy_cameras_keeps_uint8_within_its_range():
    rng = np.random.default_rng(0)
    obs = {"cameras": np.array([[[[0, 128, 255]]]], np.uint8).repeat(500, axis=1), "lidar": np.ones((2, 3), np.float32)}
    out = agreement_run.noisy_cameras(obs, 10.0, rng)
    assert out["cameras"].dtype == np.uint8 and out["lidar"] is obs["lidar"]
    assert out["cameras"][..., 0].min() == 0 and out["cameras"][..., 2].max() == 255
    assert 8.0 < float(np.std(out["cameras"][..., 1].astype(np.float32))) < 12.0


def test_the_command_builds_its_plan_from_the_run_size_and_the_flags(tmp_path, monkeypatch):
    plans = []
    monkeypatch.setattr(agreement_run, "run_agreement", lambda plan, out, **kw: plans.append(plan) or {})
    monkeypatch.setattr("m4world_env.cli._print_agreement", lambda summary, out: None)
    assert main(["agreement", "--out", str(tmp_path / "a"), "--seed", "5"]) == 0
    assert main(["agreement", "--out", str(tmp_path / "b"), "--full", "--seeds", "1", "--policies", "gap_keeper"]) == 0
    default, full = plans
    assert default.seeds == (5, 6) and default.scenarios == agreement_run.DEFAULT_SCENARIOS
    assert full.seeds == (0,) and full.policies == ("gap_keeper",) and full.scenarios == agreement_run.FULL_SCENARIOS


def test_rows_that_start_alike_share_one_first_frame(active_bundle, monkeypatch):
    """Three rows of one scene and seed and one of another in one group of rollouts: the reference
    model samples two first frames, and every row equals a vector env of its own."""
    from world_model.rollout.runtime import WorldModel

    sampled = []
    real = WorldModel.batch_first_latents

    def counting(self, cond, frames, seeds, *rest):
        sampled.append(len(frames))
        return real(self, cond, frames, seeds, *rest)

    monkeypatch.setattr(WorldModel, "batch_first_latents", counting)
    one_group = {"model": {"rollout_threads": 1}}
    shared = M4WorldVectorEnv(4, "merge_cut_in", "world_model", str(active_bundle), config=one_group)
    obs, _ = shared.reset(seed=[3, 3, 5, 3])
    assert sampled == [2]
    actions = np.array([[0.5, 0.0], [-0.5, 0.1], [0.0, 0.0], [0.5, 0.0]], dtype=np.float32)
    for _ in range(2):
        obs, *_ = shared.step(actions)
    apart = M4WorldVectorEnv(2, "merge_cut_in", "world_model", str(active_bundle))
    alone, _ = apart.reset(seed=[3, 5])
    for _ in range(2):
        alone, *_ = apart.step(actions[[1, 2]])
    for k in obs:
        assert np.array_equal(obs[k][1], alone[k][0]) and np.array_equal(obs[k][2], alone[k][1])
        assert np.array_equal(obs[k][0], obs[k][3])
    shared.close()
    apart.close()


def test_cells_in_parallel_processes_give_the_same_episodes(finished_run, active_bundle, tmp_path):
    out, summary = finished_run
    parallel = run_agreement(plan(active_bundle), tmp_path / "parallel", videos=0, jobs=2, progress=False)
    assert parallel["policies"] == summary["policies"] and parallel["jobs"] == 2
    for backend in ("procedural", "world_model"):
        name = f"episodes/{backend}/highway_dense_rain_dusk/seed1.json"
        one = json.loads((out / name).read_text())["records"]
        two = json.loads((tmp_path / "parallel" / name).read_text())["records"]
        assert one == two


KILLED_RUN = """
import multiprocessing, os
from concurrent.futures import ProcessPoolExecutor
from m4world_env.agreement.run import exit_with_parent

if __name__ == "__main__":
    pool = ProcessPoolExecutor(1, multiprocessing.get_context("spawn"), exit_with_parent, (os.getpid(),))
    print(pool.submit(os.getpid).result(), flush=True)
    os._exit(0)  # gone without a shutdown, as a killed run is
"""


def test_a_cell_worker_ends_when_the_run_is_killed(tmp_path):
    import subprocess
    import sys
    import time
    from pathlib import Path

    script = tmp_path / "killed_run.py"
    script.write_text(KILLED_RUN)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, check=True)
    worker = int(done.stdout.split()[-1])

    def running(pid: int) -> bool:  # a zombie has ended; only its parent has not reaped it
        status = Path(f"/proc/{pid}/status")
        try:
            return "\nState:\tZ" not in status.read_text()
        except FileNotFoundError:
            return False

    deadline = time.monotonic() + 10 * agreement_run.PARENT_POLL_SECONDS
    while running(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not running(worker), f"cell worker {worker} outlived the run's process"
