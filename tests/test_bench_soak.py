"""m4world bench soak end to end, small: both backends (the world model on the untrained tiny
bundle), on a 1 s scenario so that episodes restart, with the RSS samples and the exit code."""

import json
import math
from pathlib import Path

import yaml

from m4world_env.bench.soak import main
from m4world_env.scenario import SCENARIOS_DIR

EPISODE_STEPS = 5  # duration 1 s at policy_frequency 5


def _short_scenario(tmp_path: Path) -> Path:
    scenario = yaml.safe_load((SCENARIOS_DIR / "empty_highway.yaml").read_text())  # no traffic: no crash
    assert scenario["policy_frequency"] * 1.0 == EPISODE_STEPS
    path = tmp_path / "short.yaml"
    path.write_text(yaml.safe_dump({**scenario, "name": "short_empty_highway", "duration": 1.0}))
    return path


def _finite_positive(x) -> bool:
    return isinstance(x, float) and math.isfinite(x) and x > 0


def test_soak_runs_both_backends_and_reports_what_was_asked(tiny_bundle, tmp_path, capsys):
    out = tmp_path / "soak.json"
    asked = {"procedural": 12, "world_model": 6}
    args = ["--out", str(out), "--procedural-steps", "12", "--world-model-steps", "6", "--sample-every", "5"]
    args += ["--checkpoint", str(tiny_bundle), "--scenario", str(_short_scenario(tmp_path)), "--max-growth", "10"]
    assert main(args) == 0
    runs = json.loads(out.read_text())
    assert [r["backend"] for r in runs] == ["procedural", "world_model"]
    printed = capsys.readouterr().out.splitlines()
    assert len(printed) == 2
    for r, line in zip(runs, printed, strict=True):
        steps = asked[r["backend"]]
        assert r["steps"] == steps
        # an episode ends every EPISODE_STEPS steps (truncation), and each end starts a new one
        assert r["episodes"] == 1 + steps // EPISODE_STEPS
        # a sample every --sample-every steps and one at the last step
        assert [s["step"] for s in r["samples"]] == sorted({*range(5, steps + 1, 5), steps})
        assert all(_finite_positive(s["rss_mb"]) for s in r["samples"])
        assert _finite_positive(r["seconds"])
        warm = next(s for s in r["samples"] if s["step"] >= steps // 10)
        assert r["rss_after_warmup_mb"] == warm["rss_mb"] and r["rss_end_mb"] == r["samples"][-1]["rss_mb"]
        growth = (r["rss_end_mb"] - r["rss_after_warmup_mb"]) / r["rss_after_warmup_mb"]
        assert r["growth_after_warmup"] == growth and abs(growth) < 0.5
        assert line.split()[:5] == [r["backend"], str(steps), "steps,", str(r["episodes"]), "episodes,"]


def test_soak_fails_when_rss_grows_past_the_bar(tmp_path):
    """The exit code: growth after warm-up is > -100% always, so --max-growth -1 must fail; a
    zero-step world-model run is skipped (procedural only, default on-the-fly bundle unused)."""
    out = tmp_path / "soak.json"
    args = ["--out", str(out), "--procedural-steps", "3", "--world-model-steps", "0", "--sample-every", "5"]
    args += ["--scenario", str(_short_scenario(tmp_path))]
    assert main([*args, "--max-growth", "-1"]) == 1
    (run,) = json.loads(out.read_text())
    assert run["backend"] == "procedural" and run["steps"] == 3 and run["episodes"] == 1
    assert [s["step"] for s in run["samples"]] == [3]
    assert main([*args, "--max-growth", "0.5"]) == 0
