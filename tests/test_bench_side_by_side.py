"""m4world bench side_by_side, small: the ground truth's views above the world model's, per step asked."""

import numpy as np
import pytest
from PIL import Image

from m4world_env.bench.side_by_side import GAP_PX, main, views_at


def test_each_step_pairs_the_ground_truth_with_the_world_model(tiny_bundle, tmp_path):
    out = tmp_path / "pair.png"
    args = ["--checkpoint", str(tiny_bundle), "--steps", "0", "2", "--scale", "1", "--out", str(out)]
    assert main(args) == 0
    image = np.asarray(Image.open(out))
    truth = views_at("procedural", "highway_sunny_day", 3, "lane_keeping", [0, 2], None)
    v, h, w, _ = truth[0].shape
    model_h = views_at("world_model", "highway_sunny_day", 3, "lane_keeping", [0], str(tiny_bundle))[0].shape[1]
    assert image.shape == (2 * (h + model_h) + GAP_PX, v * w, 3)
    # the top row of each pair is the ground truth, exactly (PNG is lossless)
    assert np.array_equal(image[:h], np.concatenate(list(truth[0]), axis=1))
    second = h + model_h + GAP_PX
    assert np.array_equal(image[second : second + h], np.concatenate(list(truth[1]), axis=1))
    assert not np.array_equal(truth[0], truth[1])  # the episode moved on
    with pytest.raises(SystemExit):
        main(["--steps", "-1", "--out", str(out)])


def test_the_lidar_rows_show_the_range_maps_ahead(tiny_bundle, tmp_path):
    from m4world_env.bench.side_by_side import LIDAR_AHEAD_DEG, lidar_ahead

    out = tmp_path / "lidar.png"
    args = ["--checkpoint", str(tiny_bundle), "--sensor", "lidar", "--steps", "1", "--scale", "1", "--out", str(out)]
    assert main(args) == 0
    image = np.asarray(Image.open(out))
    (truth,) = views_at("procedural", "highway_sunny_day", 3, "lane_keeping", [1], None, "lidar")
    assert truth.shape[0] == 1 and image.shape[1] == truth.shape[2]
    assert np.array_equal(image[: truth.shape[1]], truth[0])  # the ground truth's range map on top
    ranges = np.full((32, 1024), 50.0, np.float32)
    ranges[:, 512] = 0.0  # no return straight ahead: black in the middle column
    strip = lidar_ahead(ranges)
    columns = 2 * round(1024 * LIDAR_AHEAD_DEG / 720.0)  # as many either side of straight ahead
    assert strip.shape[1] == 3 * columns and (strip[:, strip.shape[1] // 2] == 0).all()
