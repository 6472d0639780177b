import json
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from m4world_env.cli import main
from m4world_env.evaluate import EvalRequest, evaluate

ROOT = Path(__file__).resolve().parents[1]


def test_harness_builtin_policies_and_replayable_seeds():
    rep = evaluate(
        EvalRequest(
            "idm",
            ["merge_cut_in", "empty_highway"],
            episodes=2,
            seed=5,
            max_steps=15,
            config={"height": 32, "width": 56},
        ),
        progress=False,
    )
    assert set(rep["per_scenario"]) == {"merge_cut_in", "empty_highway"}
    for agg in [*rep["per_scenario"].values(), rep["overall"]]:
        for k in ("collision", "off_road", "progress", "ttc_violation", "comfort", "pdms"):
            assert 0.0 <= agg[k] <= 1.0
    assert [e["seed"] for e in rep["episodes"]] == [5, 6, 5, 6]
    again = evaluate(
        EvalRequest("idm", ["merge_cut_in"], episodes=1, seed=6, max_steps=15, config={"height": 32, "width": 56}),
        progress=False,
    )
    assert again["episodes"][0]["distance_m"] == rep["episodes"][1]["distance_m"]  # replay from the seed
    rand = evaluate(
        EvalRequest("random", ["merge_cut_in"], episodes=1, seed=0, max_steps=10, config={"height": 32, "width": 56}),
        progress=False,
    )
    assert rand["overall"]["episodes"] == 1


def test_eval_cli_custom_policy_table_and_json(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "eval",
                "--policy",
                "tests.policy_fixture:brake",
                "--scenarios",
                "empty_highway",
                "--episodes",
                "1",
                "--max-steps",
                "5",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "pdms" in text and "OVERALL" in text
    rep = json.loads(out.read_text())
    assert rep["policy"] == "tests.policy_fixture:brake" and len(rep["episodes"]) == 1
    assert main(["eval", "--policy", "no_such_module:f", "--scenarios", "empty_highway"]) == 2
    assert "cannot load policy" in capsys.readouterr().err
    assert main(["eval", "--policy", "tests.policy_fixture:make_braker", "--scenarios", "empty_highway"]) == 0
    assert "OVERALL" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # argparse: usage error, exit status 2
        main(["eval", "--episodes", "0", "--scenarios", "empty_highway"])
    assert "--episodes: must be a positive integer" in capsys.readouterr().err


@pytest.mark.slow
def test_sb3_ppo_example_runs_a_few_hundred_steps(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["train_ppo.py"])
    mod = runpy.run_path(str(ROOT / "examples" / "train_ppo.py"))
    report = mod["main"](
        [
            "--timesteps",
            "256",
            "--num-envs",
            "2",
            "--height",
            "40",
            "--width",
            "72",
            "--eval-episodes",
            "1",
            "--eval-max-steps",
            "20",
            "--out",
            str(tmp_path),
        ]
    )
    assert (tmp_path / "ppo_m4world.zip").exists() and (tmp_path / "eval.json").exists()
    assert np.isfinite(report["overall"]["pdms"])


def test_an_eval_request_is_checked_when_made_before_any_env_exists():
    for bad, message in (
        ({"episodes": 0}, "episodes must be a positive integer, got 0"),
        ({"episodes": True}, "episodes must be a positive integer"),
        ({"max_steps": 0}, "max_steps must be a positive integer or None"),
    ):
        with pytest.raises(ValueError, match=message):
            EvalRequest("idm", ["merge_cut_in"], **bad)
    with pytest.raises(ValueError, match="list of scenario names or paths, got the string 'merge_cut_in'"):
        EvalRequest("idm", "merge_cut_in")
    assert EvalRequest("idm", ["merge_cut_in", "empty_highway"]).scenarios == ("merge_cut_in", "empty_highway")
