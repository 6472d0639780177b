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
