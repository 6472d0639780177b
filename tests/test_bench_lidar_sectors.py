"""m4world bench lidar_sectors, small: the ground truth read against itself has no error, a model
that loses every object misses them all, and the command writes the figures per scenario and band
with the world model (the untrained tiny bundle) fed the ground truth's actions."""

import json

import numpy as np
import pytest

from m4world_env.bench.lidar_sectors import ALL, COLUMNS, compare, episode, figures, main, world_model_kwargs
from world_model.eval.decisions import BEAM_BANDS

BANDS = [b.name for b in BEAM_BANDS]


def test_the_ground_truth_against_itself_reads_every_object_exactly():
    truths, models, spec = episode("highway_sunny_day", 0, 4, {"backend": "procedural"})
    assert len(truths) == len(models) == 4
    same = figures(compare(truths, models, spec))
    assert same["all"]["objects"] > 0 and same["horizon"]["objects"] > 0
    for band in BANDS:
        f = same[band]
        assert f["median_error_m"] in (0.0, None) and f["phantom"] == 0.0
        assert f["farther_or_missed"] in (0.0, None) and f["missed"] in (0.0, None)
        assert f["close_off"] in (0.0, None)
    # a model that reports no return anywhere misses every object; one 10 m farther is farther (or
    # misses those whose pushed returns sink into the road)
    blind = figures(compare(truths, [np.full_like(t, spec.no_return) for t in truths], spec))["all"]
    assert blind["objects"] == same["all"]["objects"] and blind["missed"] == blind["farther_or_missed"] == 1.0
    far = [np.where(t != spec.no_return, t + 10.0, t) for t in truths]
    pushed = figures(compare(truths, far, spec))["all"]
    assert pushed["farther_or_missed"] == 1.0 and pushed["median_error_m"] > 9.99  # float32 ranges
    # a tenth of a metre nearer is off in the close field only
    nearer = figures(compare(truths, [np.where(t != spec.no_return, t - 0.15, t) for t in truths], spec))["all"]
    assert nearer["farther_or_missed"] == 0.0 and (nearer["close_objects"] == 0 or nearer["close_off"] == 1.0)
    with pytest.raises(ValueError):  # one range map short
        compare(truths, models[:-1], spec)


def test_the_command_writes_each_scenario_and_band_and_their_pool(tiny_bundle, tmp_path):
    out = tmp_path / "ls.json"
    scenarios = ["highway_sunny_day", "merge_cut_in"]
    args = ["--scenarios", *scenarios, "--seeds", "0", "--steps", "2", "--checkpoint", str(tiny_bundle)]
    assert main([*args, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["scenarios"] == scenarios and result["seeds"] == [0] and result["steps"] == 2
    assert result["checkpoint"] == str(tiny_bundle)
    assert result["steps_run"] == {s: {"0": 2} for s in scenarios}
    assert list(result["results"]) == [*scenarios, ALL]
    for name, bands in result["results"].items():
        assert list(bands) == BANDS, name
        assert all(set(COLUMNS) <= set(f) for f in bands.values())
    for band in BANDS:  # the pool adds the scenarios' sectors
        for count in ("objects", "empty"):
            assert result["results"][ALL][band][count] == sum(result["results"][s][band][count] for s in scenarios)
    assert world_model_kwargs(None) == {"backend": "world_model", "config": {"observation_keys": ["lidar"]}}


def test_bad_arguments_are_refused_before_any_episode(tmp_path):
    for bad in (["--steps", "0"], ["--seeds", "-1"], ["--scenarios", "no_such_scenario"]):
        with pytest.raises(SystemExit) as done:
            main([*bad, "--out", str(tmp_path / "ls.json")])
        assert done.value.code == 2
