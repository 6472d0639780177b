"""train_segmenter: runs end to end on tiny recordings, resumes to the same weights as an
uninterrupted run, measures held-out clips, and refuses what it must."""

import json

import numpy as np
import pytest
from safetensors.numpy import load_file

from m4world_env.recorder import RecordConfig, record
from world_model.eval.segmenter import CONFIG_FILE, SCENE_CLASSES, WEIGHTS_FILE, SegmenterConfig, load_segmenter
from world_model.eval.segmenter_data import cached_scene_labels
from world_model.eval.train_segmenter import (
    AugmentConfig,
    TrainSegmenterConfig,
    augment,
    class_weights,
    main,
    train_segmenter,
)


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("segmenter_data")
    for name, seed in (("train", 0), ("heldout", 500)):
        cfg = RecordConfig(scenarios=["highway_sunny_day"], duration=1.0, out=root / name, seed=seed)
        record(cfg, progress=False)
    return root / "train", root / "heldout"


def _cfg(**kw) -> TrainSegmenterConfig:
    small = {"net": SegmenterConfig(channels=(4, 8), head_channels=4), "steps": 4, "batch_size": 4}
    small |= {"train_stride": 5, "heldout_stride": 5, "check_frames": 1, "ckpt_every": 2, "log_every": 1}
    return TrainSegmenterConfig(**(small | kw))


def test_a_resumed_run_ends_with_the_weights_of_an_uninterrupted_one(dirs, tmp_path):
    train, held = dirs
    logs: list[str] = []
    seg = train_segmenter([train], [held], tmp_path / "a", tmp_path / "work_a", config=_cfg(), log=logs.append)
    assert seg is not None and any(line.startswith("held-out IoU road") for line in logs)
    stopped = train_segmenter([train], [held], tmp_path / "b", tmp_path / "work_b", config=_cfg(), max_minutes=0.0,
                              log=lambda s: None)  # fmt: skip
    assert stopped is None and not (tmp_path / "b").exists()
    assert json.loads((tmp_path / "work_b" / "progress.json").read_text())["step"] == 1
    train_segmenter([train], [held], tmp_path / "b", tmp_path / "work_b", config=_cfg(), log=logs.append)
    assert "resuming at step 1" in logs
    wa, wb = load_file(str(tmp_path / "a" / WEIGHTS_FILE)), load_file(str(tmp_path / "b" / WEIGHTS_FILE))
    assert wa.keys() == wb.keys()
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k])
    loaded = load_segmenter(tmp_path / "a")
    info = loaded.info
    assert set(info["heldout"]["iou"]) == set(SCENE_CLASSES) and info["heldout"]["clips"] == 1
    assert info["heldout"]["views"] == 3 * 6  # frames 0, 5 and 10 of an 11-frame clip, six cameras
    held_clip = json.loads((held / "dataset.json").read_text())["clips"][0]
    assert info["check_slice"]["clip"] == held_clip and info["check_slice"]["frames"] == [0]
    # Absolute paths are written by folder name only: shipped metadata names no machine path.
    assert "--data train --heldout heldout --work work_a --out a" in info["command"]
    assert str(tmp_path) not in (tmp_path / "a" / CONFIG_FILE).read_text()


def test_label_maps_are_cached_once(dirs, tmp_path):
    from world_model.data import list_clips, read_clip

    train, _ = dirs
    clip = read_clip(train, list_clips(train)[0])
    first = cached_scene_labels(clip, tmp_path)
    files = list(tmp_path.glob("*.npy"))
    assert len(files) == 1 and first.shape == clip.cameras.shape[:4]
    again = cached_scene_labels(clip, tmp_path)
    assert isinstance(again, np.memmap)  # read back, not computed again
    np.testing.assert_array_equal(first, again)


def test_class_weights_favour_rare_classes_with_a_cap():
    labels = np.zeros(1000, np.uint8)
    labels[:10] = 3  # vehicle: 1 %
    w = class_weights(labels, power=0.5, max_weight=5.0)
    assert w[3] > w[0] and w[3] <= 5.0
    assert w[1] == 5.0  # never labelled: the cap


def test_augmenting_a_night_view_keeps_the_road_darker_than_the_ground():
    # an unlit night view: the road two levels darker than the ground beside it, noise and blur off
    image = np.full((1, 16, 16, 3), 11, np.uint8)
    image[:, 8:, 4:12] = 9
    labels = np.zeros((1, 16, 16), np.uint8)
    labels[:, 8:, 4:12] = SCENE_CLASSES.index("road")
    config = AugmentConfig(blur=0.0, noise=0.0, channel_gain=0.0)
    for seed in range(50):
        x, y = augment(image, labels, np.random.default_rng(seed), config)
        road = x[0][:, y[0] == SCENE_CLASSES.index("road")]
        ground = x[0][:, y[0] == 0]
        assert road.max() < ground.min(), f"seed {seed}: the augmented view no longer shows the road"


def test_bad_inputs_are_specific(dirs, tmp_path):
    train, held = dirs
    with pytest.raises(ValueError, match="must not be training clips"):
        train_segmenter([train], [train], tmp_path / "x", tmp_path / "w", config=_cfg())
    train_segmenter([train], [held], tmp_path / "x", tmp_path / "w", config=_cfg(), max_minutes=0.0, log=lambda s: None)
    with pytest.raises(ValueError, match="other settings"):
        train_segmenter([train], [held], tmp_path / "x", tmp_path / "w", config=_cfg(lr=1e-4))
    with pytest.raises(ValueError, match="not an m4world dataset"):
        train_segmenter([tmp_path], [held], tmp_path / "x", tmp_path / "w2", config=_cfg())
    with pytest.raises(SystemExit):
        main(["--data", str(train), "--heldout", str(held), "--work", "w", "--out", "o", "--steps", "0"])
