"""m4world bench lane_markings, small: a view's markings and road are read from its label map, the
ground truth read against itself has a contrast ratio of 1, and the command writes the figures per
scenario with the world model (the untrained tiny bundle) fed the ground truth's actions."""

import json

import numpy as np
import pytest

from m4world_env.bench.lane_markings import MIN_MARKING_PIXELS, episode, figures, front_reading, main
from world_model.raster.classes import MARKING, ROAD, SKY


def test_a_reading_is_the_lower_halfs_markings_and_road():
    classes = np.full((8, 10), ROAD, np.uint8)
    classes[:4] = SKY
    classes[6, 2:8] = MARKING
    classes[1, :] = MARKING  # in the upper half: not read
    image = np.full((8, 10, 3), 50, np.uint8)
    image[6, 2:8] = (200, 210, 190)
    image[1] = 0
    assert front_reading(image, classes) == (200.0, 50.0)
    classes[6, 2 + MIN_MARKING_PIXELS - 1 :] = ROAD  # too few markings left to read
    assert front_reading(image, classes) is None
    with pytest.raises(ValueError, match="differ in size"):
        front_reading(image[:, :-1], classes)


def test_figures_pool_the_readings_and_say_how_the_contrasts_compare():
    f = figures([((200.0, 50.0), (150.0, 50.0)), ((100.0, 50.0), (150.0, 50.0))])
    assert f["frames"] == 2 and f["marking_truth"] == f["marking_model"] == 150.0
    assert f["contrast_truth"] == f["contrast_model"] == 3.0 and f["contrast_ratio"] == 1.0
    assert figures([])["frames"] == 0 and figures([])["contrast_ratio"] is None


def test_the_ground_truth_against_itself_reads_the_same_markings():
    pairs = episode("highway_sunny_day", 0, 3, {"backend": "procedural"})
    assert len(pairs) == 3 and all(truth == model for truth, model in pairs)
    assert figures(pairs)["contrast_ratio"] == 1.0 and figures(pairs)["contrast_truth"] > 1.5  # white on grey


def test_the_command_writes_each_scenario(tiny_bundle, tmp_path):
    out = tmp_path / "lm.json"
    args = ["--scenarios", "highway_sunny_day", "--seeds", "0", "--steps", "2", "--checkpoint", str(tiny_bundle)]
    assert main([*args, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["scenarios"] == ["highway_sunny_day"] and result["steps"] == 2
    assert set(result["results"]) == {"highway_sunny_day"} and result["results"]["highway_sunny_day"]["frames"] <= 2
    with pytest.raises(SystemExit):
        main(["--scenarios", "no_such_scenario", "--out", str(tmp_path / "x.json")])
