"""The evaluation set's definition: coverage, held-out seeds, recording."""

import pytest

from m4world_env.evalset import EvalsetConfig, evalset_plan, load_manifest, record_evalset
from m4world_env.recorder import SCENARIO_KEYS, episode_seed
from m4world_env.scenario import list_scenarios
from world_model.data import read_clip
from world_model.scene import CATEGORIES, TIMES_OF_DAY, WEATHERS


def test_default_plan_covers_roads_weathers_times_categories_and_long_clips():
    jobs = evalset_plan()
    d = [j.describe() for j in jobs]
    assert {e["road"] for e in d} == {"highway", "merge", "roundabout", "intersection", "two_way"}
    assert {(e["weather"], e["time_of_day"]) for e in d if e["kind"] == "grid"} == {
        (w, t) for w in WEATHERS for t in TIMES_OF_DAY
    }
    for e in d:
        if e["kind"] == "grid":
            assert e["scripted_categories"] == sorted(CATEGORIES)
    assert {e["scenario"] for e in d if e["kind"] == "scenario"} == set(list_scenarios())
    long = [j for j in jobs if j.kind == "long"]
    assert len(long) >= 3 and all(j.scenario.duration * j.scenario.sensor_frequency >= 600 for j in long)
    assert len({j.name for j in jobs}) == len(jobs)


def test_seeds_are_disjoint_from_training():
    train = {episode_seed(0, key, e) for key in range(SCENARIO_KEYS) for e in range(5000)}
    assert not train & {j.seed for j in evalset_plan()}
    with pytest.raises(ValueError, match="collide with training"):
        EvalsetConfig(base_seed=0)


def test_plan_is_deterministic():
    a, b = evalset_plan(), evalset_plan()
    assert [j.describe() for j in a] == [j.describe() for j in b]
    assert [j.scenario for j in a] == [j.scenario for j in b]


def test_record_small_evalset(tmp_path):
    cfg = EvalsetConfig(
        scenarios=("merge_cut_in",),
        episodes_per_scenario=1,
        short_duration=1.0,
        grid_weathers=("fog",),
        grid_times=("night",),
        long_scenarios=(),
    )
    entries = record_evalset(tmp_path, cfg, progress=False)
    assert [e["kind"] for e in entries] == ["scenario", "grid"]
    assert load_manifest(tmp_path, kinds=["grid"])[0]["weather"] == "fog"
    clip = read_clip(tmp_path, entries[1]["name"])
    assert clip.num_frames == 11 and clip.frames[0].prompt.time_of_day == "night"
    assert {o.category for o in clip.frames[0].objects} >= set(CATEGORIES)
    # Resumable: a second call records nothing new and returns the same entries.
    assert record_evalset(tmp_path, cfg, progress=False) == entries
