"""m4world bench action_response end to end, small: the procedural backend's response to braking
is the ground truth (response 1), a world-model backend (the untrained tiny bundle) is scored
against it, and bad arguments are refused."""

import json
import statistics

import numpy as np
import pytest

from m4world_env.bench.action_response import MOVED_M, add_responses, apart, main, split_mean, summarize


def test_braking_moves_the_ground_truth_and_each_backend_is_scored_against_it(tiny_bundle, tmp_path):
    out = tmp_path / "response.json"
    args = ["--out", str(out), "--steps", "4", "--checkpoint", str(tiny_bundle)]
    assert main([*args, "--backend", "procedural", "world_model:sink=0"]) == 0
    result = json.loads(out.read_text())
    truth, model = result["backends"]["procedural"], result["backends"]["world_model:sink=0"]
    assert truth["steps"] == model["steps"] == 4
    # Same seed, same scene at reset; braking leaves the held-speed run behind from the first step.
    assert truth["per_step"]["cameras"][0] == 0.0 and truth["per_step"]["lidar"][0] == 0.0
    assert all(d > 0 for d in truth["per_step"]["cameras"][1:]) and truth["median_lidar"] > 0
    assert truth["response_cameras"] == 1.0 and truth["response_lidar"] == 1.0
    # The world model's two runs draw the same noise: identical at reset, only the action differs.
    assert model["per_step"]["cameras"][0] == 0.0 and model["per_step"]["lidar"][0] == 0.0
    for k in ("cameras", "lidar", "lidar_moved"):  # its medians over the steps, over the truth's
        steps = statistics.median(model["per_step"][k][1:])
        assert model[f"median_{k}"] == steps and model[f"response_{k}"] == steps / truth[f"median_{k}"]
    # The LiDAR split by where the truth moved: the truth changes more there than anywhere else.
    assert truth["response_lidar_moved"] == 1.0 and truth["median_lidar_moved"] > MOVED_M
    assert max(truth["per_step"]["lidar_still"]) <= MOVED_M
    assert model["per_step"]["lidar_moved"][0] == 0.0


def test_a_response_is_the_median_over_the_steps_against_the_ground_truths():
    """Step 0 (the reset, alike in both runs) is left out of the medians; a ground truth that did
    not move gives no response rather than a division by zero."""
    truth = summarize({"cameras": [9.0, 2.0, 4.0, 6.0], "lidar": [0.0, 1.0, 1.0, 1.0], "lidar_moved": [0.0] * 4})
    model = summarize({"cameras": [0.0, 1.0, 1.0, 3.0], "lidar": [5.0, 3.0, 0.5, 2.0], "lidar_moved": [1.0] * 4})
    backends = {"truth": truth, "model": model}
    add_responses(backends, truth="truth")
    assert truth["steps"] == model["steps"] == 3
    assert (truth["median_cameras"], model["median_cameras"]) == (4.0, 1.0)
    assert model["response_cameras"] == 0.25 and model["response_lidar"] == 2.0
    assert truth["response_cameras"] == truth["response_lidar"] == 1.0
    assert model["response_lidar_moved"] is None and truth["response_lidar_moved"] is None


def test_the_lidar_difference_splits_by_where_the_truth_moved():
    assert split_mean(np.array([1.0, 2.0, 3.0, 5.0]), np.array([True, False, False, True])) == (3.0, 2.5)
    assert split_mean(np.array([1.0, 3.0]), np.zeros(2, bool)) == (0.0, 2.0)
    frame = {"cameras": np.zeros((1, 2, 2, 3), np.uint8)}
    a = [{**frame, "lidar": np.zeros((2, 2), np.float32)}] * 2
    b = [{**frame, "lidar": np.zeros((2, 2), np.float32)}, {**frame, "lidar": np.array([[4, 0], [0, 1]], np.float32)}]
    moved = [np.zeros((2, 2), bool), np.array([[True, False], [False, False]])]
    curves = apart(a, b, moved)
    assert curves["lidar"] == [0.0, 1.25] and curves["lidar_moved"] == [0.0, 4.0]
    assert curves["lidar_still"] == pytest.approx([0.0, 1 / 3])


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="comma-separated numbers"):
        main(["--out", str(tmp_path / "r.json"), "--actions", "0,0", "brake"])
    with pytest.raises(SystemExit):  # argparse: no ground truth to divide by
        main(["--out", str(tmp_path / "r.json"), "--backend", "world_model"])
