"""m4world tune-range-head: the range head tuned on the env's own rollouts, in a new bundle that
changes nothing else."""

import numpy as np
import torch

from m4world_env.cli import main as cli_main
from m4world_env.range_tuning import close_field, train
from world_model.bundle import load_bundle_files
from world_model.model.layout import RANGE_LEVELS
from world_model.model.range_head import RangeHead
from world_model.model.vae import ranges_to_image_values
from world_model.sensors import LidarSpec
from world_model.train.range_head_stage import RangeExamples

SPEC = LidarSpec(beams=8, azimuth=96, max_range=100.0)
NO_RETURN_FRACTION = 0.97


def car_alongside(frames: int) -> RangeExamples:
    """A car 3 m to the left on every beam above the road, the decoder's view of it a smear at ~12 m."""
    ranges = np.zeros((frames, SPEC.beams, SPEC.azimuth), np.float32)  # no return
    ranges[:, :4, 20:28] = 3.0
    near = np.where(ranges > 0, np.rint((1 - ranges / SPEC.max_range) * RANGE_LEVELS), 0).astype(np.uint16)
    targets = ranges_to_image_values(torch.from_numpy(ranges), SPEC)[:, None]
    views = torch.full((frames, 1, 4, 12), 1.0)
    views[:, :, :2, 2:4] = -0.76  # ~12 m
    return RangeExamples(views, torch.from_numpy(near), targets, torch.from_numpy(ranges > 0)[:, None])


def test_tuning_stands_the_close_field_where_the_scene_puts_it():
    examples = car_alongside(4)
    untrained = RangeHead().eval()  # the stretched view: the smear, far off
    before = close_field(untrained, examples, SPEC, NO_RETURN_FRACTION)
    assert before["close_objects"] > 0 and before["close_off"] == 1.0
    tuned = train(untrained, examples, steps=150)
    assert close_field(tuned, examples, SPEC, NO_RETURN_FRACTION)["close_off"] == 0.0
    assert not any(p.requires_grad for p in tuned.parameters())
    assert torch.equal(untrained.net[-1].weight, torch.zeros_like(untrained.net[-1].weight))  # a copy was trained


def test_the_command_writes_a_bundle_that_differs_in_the_range_head_only(range_head_bundle, tmp_path):
    out = tmp_path / "tuned"
    args = ["--checkpoint", str(range_head_bundle), "--out", str(out), "--seeds", "0", "--steps", "3"]
    assert cli_main(["tune-range-head", *args, "--train-steps", "2"]) == 0
    source, tuned = load_bundle_files(range_head_bundle), load_bundle_files(out)  # both verify
    record = tuned.manifest["components"]["vae"]["tuned"]
    assert record["seeds"] == [0] and record["steps"] == 3 and record["train_steps"] == 2
    assert record["frames"] == 2 * len(record["scenarios"])  # the first step of each episode is skipped
    assert set(record["close_field_after"]) == {"close_objects", "close_off"}
    moved = []
    for name, tensors in source.tensors.items():
        for key, value in tensors.items():
            if name == "vae" and key.startswith("range_head."):
                moved.append(not torch.equal(value, tuned.tensors[name][key]))
            else:
                assert torch.equal(value, tuned.tensors[name][key]), (name, key)
    assert any(moved)
    assert not (tmp_path / "tuned.partial").exists()


def test_a_bundle_without_a_range_head_is_refused_before_any_episode(tiny_bundle, tmp_path, capsys):
    assert cli_main(["tune-range-head", "--checkpoint", str(tiny_bundle), "--out", str(tmp_path / "x")]) != 0
    err = capsys.readouterr().err
    assert "VAE has no range head to tune" in err and "frames in all" not in err
    assert not (tmp_path / "x").exists()
