"""m4world bench policy_reads, small: every zoo member's two copies decide alike on the ground
truth read twice, the figures pool the steps per member (absolute and signed), and the command
writes every member of each scenario with the world model (the untrained tiny bundle) fed the
ground truth's actions."""

import json

import numpy as np
import pytest

from m4world_env import zoo
from m4world_env.bench.policy_reads import episode, figures, main, table

MEMBERS = ["gap_keeper", "gap_keeper_lidar_noise", "bc_cameras_small"]


def test_the_ground_truth_read_twice_gives_every_member_the_same_actions():
    steps = episode("merge_cut_in", 0, 3, {"backend": "procedural"}, MEMBERS)
    assert len(steps) == 3 and all(s.shape == (len(MEMBERS), 2) for s in steps)
    assert all(np.all(s == 0.0) for s in steps)  # seeded noise included: both copies share the seed


def test_the_figures_are_per_member_absolute_and_signed():
    differences = [np.array([[0.2, -0.1], [0.0, 0.0]]), np.array([[-0.2, -0.3], [0.0, 0.1]])]
    f = figures(differences, ["a", "b"])
    assert f["a"] == pytest.approx({"accel": 0.2, "steer": 0.2, "steer_bias": -0.2})
    assert f["b"] == pytest.approx({"accel": 0.0, "steer": 0.05, "steer_bias": 0.05})
    assert figures([], ["a"]) == {}
    assert "| s | a | 0.200 | 0.200 | -0.200 |" in table({"s": f})


def test_the_command_writes_every_member(tiny_bundle, tmp_path):
    out = tmp_path / "pr.json"
    args = ["--scenarios", "merge_cut_in", "--seeds", "0", "--steps", "2", "--checkpoint", str(tiny_bundle)]
    assert main([*args, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["members"] == list(zoo.members())
    per = result["results"]["merge_cut_in"]
    assert set(per) == set(zoo.members()) and all(set(f) == {"accel", "steer", "steer_bias"} for f in per.values())
    with pytest.raises(SystemExit):
        main(["--scenarios", "no_such_scenario", "--out", str(tmp_path / "x.json")])
