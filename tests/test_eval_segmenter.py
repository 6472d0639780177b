"""The segmenter and the scene IoU: class mapping, network shapes, sealed persistence, per-second IoU,
and the shipped weights reproducing their recorded held-out figure."""

import json
import shutil

import numpy as np
import pytest
import torch

from world_model import Box3D, EgoState, SceneFrame, SceneObject, default_rig
from world_model.eval.scene_iou import SceneIoU, pool_scene_iou, scene_iou, scene_labels
from world_model.eval.segmenter import (
    CONFIG_FILE,
    DEFAULT_SEGMENTER_DIR,
    NUM_SCENE_CLASSES,
    SCENE_CLASSES,
    WEIGHTS_FILE,
    Segmenter,
    SegmenterConfig,
    SegNet,
    load_default_segmenter,
    load_segmenter,
    scene_classes,
)
from world_model.raster.classes import LABEL_CLASSES
from world_model.sim.demo import straight_road
from world_model.sim.labels import LabelRasterizer

BACKGROUND, ROAD, MARKING, VEHICLE, VULNERABLE, OTHER = range(NUM_SCENE_CLASSES)
RIG = default_rig(width=112, height=64)
FRONT = 1


def test_every_label_class_maps_onto_its_scene_class():
    ids = np.arange(len(LABEL_CLASSES), dtype=np.uint8)
    mapped = dict(zip(LABEL_CLASSES, scene_classes(ids).tolist(), strict=True))
    assert mapped == {
        "sky": BACKGROUND,
        "offroad": BACKGROUND,
        "road": ROAD,
        "marking": MARKING,
        "vehicle": VEHICLE,
        "vulnerable": VULNERABLE,
        "other_object": OTHER,
    }
    assert scene_classes(np.zeros((2, 3), np.int64)).shape == (2, 3)
    with pytest.raises(ValueError, match="outside"):
        scene_classes(np.array([len(LABEL_CLASSES)]))
    with pytest.raises(ValueError, match="integer"):
        scene_classes(np.array([0.5]))


def test_scene_labels_of_a_hand_built_scene():
    """Ego on the middle lane of a straight 3-lane road (y in [-10, 2]), a car 15 m ahead, a
    pedestrian on the left verge, a cone on the right shoulder."""
    road = straight_road(num_lanes=3)

    def obj(tid, x, y, category, size):
        return SceneObject(tid, category, Box3D((x, y, size[2] / 2), size, 0.0), color=(90, 90, 90))

    objects = (
        obj("car", 15.0, -4.0, "car", (4.5, 1.9, 1.6)),
        obj("walker", 12.0, 3.5, "pedestrian", (0.6, 0.6, 1.8)),
        obj("cone", 10.0, -9.0, "cone", (0.4, 0.4, 0.7)),
    )
    frame = SceneFrame(0.0, 0, EgoState(0.0, -4.0, 0.0), objects, road, rig=RIG)
    labels = scene_labels([frame, frame], 64, 112)
    assert labels.shape == (2, 6, 64, 112) and labels.dtype == np.uint8
    raw = LabelRasterizer()(frame, RIG, 64, 112)
    np.testing.assert_array_equal(labels[0], scene_classes(raw))
    front = labels[0, FRONT]
    assert front[0, 56] == BACKGROUND  # sky above the horizon
    assert front[63, 56] == ROAD  # the ego's lane just ahead of the bumper
    assert front[36, 56] == VEHICLE  # the car straight ahead
    for c in (MARKING, VULNERABLE, OTHER):
        assert np.any(front == c), SCENE_CLASSES[c]
    # Without the objects, the car's pixels are road or marking again, never background.
    empty = scene_labels([SceneFrame(0.0, 0, frame.ego, (), road, rig=RIG)], 64, 112)[0, FRONT]
    assert empty[36, 56] in (ROAD, MARKING)
    with pytest.raises(ValueError, match="at least one frame"):
        scene_labels([], 64, 112)


def test_segnet_shapes_and_predictions():
    net = SegNet(SegmenterConfig(channels=(4, 8), head_channels=4))
    assert net(torch.rand(2, 3, 16, 28)).shape == (2, NUM_SCENE_CLASSES, 16, 28)
    with pytest.raises(ValueError, match="divisible by 4"):
        net(torch.rand(1, 3, 15, 28))
    seg = Segmenter(net, batch_size=5)
    frames = np.random.default_rng(0).integers(0, 256, (3, 2, 16, 28, 3), dtype=np.uint8)
    pred = seg.predict(frames)
    assert pred.shape == (3, 2, 16, 28) and pred.dtype == np.uint8 and pred.max() < NUM_SCENE_CLASSES
    np.testing.assert_array_equal(pred[1], seg.predict(frames[1]))  # batching does not change the answer
    with pytest.raises(ValueError, match="uint8"):
        seg.predict(frames.astype(np.float32))


def test_save_load_round_trip_and_the_seal(tmp_path):
    torch.manual_seed(0)
    seg = Segmenter(SegNet(SegmenterConfig(channels=(4, 8), head_channels=4)), info={"note": "x"})
    seg.save(tmp_path / "a")
    loaded = load_segmenter(tmp_path / "a")
    frames = np.random.default_rng(1).integers(0, 256, (2, 16, 28, 3), dtype=np.uint8)
    np.testing.assert_array_equal(loaded.predict(frames), seg.predict(frames))
    assert loaded.info == {"note": "x"}
    # An edited JSON is refused.
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    meta = json.loads((tmp_path / "b" / CONFIG_FILE).read_text())
    meta["info"]["note"] = "y"
    (tmp_path / "b" / CONFIG_FILE).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="digest"):
        load_segmenter(tmp_path / "b")
    # Replaced weights are refused.
    shutil.copytree(tmp_path / "a", tmp_path / "c")
    Segmenter(SegNet(SegmenterConfig(channels=(4, 8), head_channels=4))).save(tmp_path / "other")
    shutil.copy(tmp_path / "other" / WEIGHTS_FILE, tmp_path / "c" / WEIGHTS_FILE)
    with pytest.raises(ValueError, match="weights_sha256"):
        load_segmenter(tmp_path / "c")
    with pytest.raises(FileNotFoundError, match="train_segmenter"):
        load_segmenter(tmp_path / "missing")


class _ChannelSegmenter(Segmenter):
    """Reads the class straight from the red channel: a segmenter whose answers a test can write."""

    def __init__(self) -> None:
        self.calls = 0

    def predict(self, images: np.ndarray) -> np.ndarray:
        self.calls += 1
        return images[..., 0].copy()


def test_scene_iou_per_second_and_last_window_by_hand():
    # 2 fps, 5 frames: seconds {0, 1} and {2, 3}; frame 4 is a partial second, dropped.
    labels = np.zeros((5, 1, 1, 2), np.uint8)
    labels[..., 1] = VEHICLE  # every frame: pixel 0 background, pixel 1 vehicle
    gen = np.zeros((5, 1, 1, 2, 3), np.uint8)
    gen[:2, 0, 0, 1, 0] = VEHICLE  # second 0: right everywhere
    gen[2, 0, 0, :, 0] = VEHICLE  # second 1: one frame paints the background as a vehicle,
    gen[3, 0, 0, :, 0] = BACKGROUND  # the other loses the vehicle
    gen[4, 0, 0, :, 0] = ROAD
    seg = _ChannelSegmenter()
    r = scene_iou(gen, labels, fps=2, segmenter=seg, window_s=1)
    assert isinstance(r, SceneIoU) and len(r.per_second) == 2 and r.window_s == 1
    first, second = r.per_second_iou()
    assert first["background"] == 1.0 and first["vehicle"] == 1.0 and first["road"] is None
    # Second 1: background labelled {f2p0, f3p0}, predicted {f3p0, f3p1}: 1 / 3; vehicle labelled
    # {f2p1, f3p1}, predicted {f2p0, f2p1}: 1 / 3.
    assert second["background"] == pytest.approx(1 / 3) and second["vehicle"] == pytest.approx(1 / 3)
    assert r.last_window_iou() == second
    whole = scene_iou(gen, labels, fps=2, segmenter=seg, window_s=10)
    assert whole.window_s == 2  # a clip shorter than the window: all of it
    assert whole.last_window_iou()["vehicle"] == pytest.approx(3 / 5)  # intersection 3, union 5
    strided = scene_iou(gen, labels, fps=2, segmenter=seg, window_s=1, frame_stride=2)
    assert strided.per_second_iou()[1]["vehicle"] == pytest.approx(1 / 2)  # frame 2 only
    pooled = pool_scene_iou([r, scene_iou(gen[:2], labels[:2], fps=2, segmenter=seg, window_s=1)])
    assert len(pooled.per_second) == 2 and pooled.per_second_iou()[0]["vehicle"] == 1.0
    assert pooled.last_window_iou()["vehicle"] == pytest.approx(3 / 5)  # second 1 of r + second 0 of the short clip


def test_scene_iou_bad_input_is_specific():
    seg = _ChannelSegmenter()
    gen, labels = np.zeros((4, 1, 2, 2, 3), np.uint8), np.zeros((4, 1, 2, 2), np.uint8)
    with pytest.raises(ValueError, match="fps"):
        scene_iou(gen, labels, fps=2.5, segmenter=seg)
    with pytest.raises(ValueError, match="labels must be"):
        scene_iou(gen, labels[:, :, :1], fps=2, segmenter=seg)
    with pytest.raises(ValueError, match="at least one second"):
        scene_iou(gen, labels, fps=10, segmenter=seg)
    with pytest.raises(ValueError, match="uint8"):
        scene_iou(gen.astype(np.float32), labels, fps=2, segmenter=seg)
    a = scene_iou(gen, labels, fps=2, segmenter=seg, window_s=1)
    b = scene_iou(gen, labels, fps=2, segmenter=seg, window_s=2)
    with pytest.raises(ValueError, match="different lengths"):
        pool_scene_iou([a, b])


def test_the_shipped_segmenter_reproduces_its_held_out_check_slice():
    """Re-record the held-out clip named in segmenter.json and measure the shipped weights on the
    slice it names: the IoU must be the one recorded at training time."""
    from m4world_env.recorder import RecordConfig, record_episode
    from m4world_env.scenario import load_scenario

    seg = load_default_segmenter()
    meta = json.loads((DEFAULT_SEGMENTER_DIR / CONFIG_FILE).read_text())
    assert meta["scene_classes"] == list(SCENE_CLASSES)
    info = seg.info
    assert set(info["heldout"]["iou"]) == set(SCENE_CLASSES)
    check = info["check_slice"]
    rec = check["recording"]
    cfg = RecordConfig(
        scenarios=[check["scenario"]],
        randomize=rec["randomize"],
        duration=rec["duration"],
        height=rec["height"],
        width=rec["width"],
        action_type=rec["action_type"],
        exclude_categories=tuple(rec["exclude_categories"]),
        styles=tuple(rec.get("styles", ["steady"])),
    )
    frames, cameras, *_ = record_episode(load_scenario(check["scenario"]), check["seed"], cfg)
    picked = check["frames"]
    labels = scene_labels([frames[t] for t in picked], rec["height"], rec["width"])
    r = scene_iou(cameras[picked], labels, fps=1, segmenter=seg, window_s=len(picked))
    for name, value in r.last_window_iou().items():
        expected = check["iou"][name]
        if expected is None:
            assert value is None, name
        else:
            assert value == pytest.approx(expected, abs=0.01), name


@pytest.mark.parametrize(
    ("sky", "ground"),
    [((170, 195, 225), (70, 115, 55)), ((215, 218, 225), (200, 202, 206)), ((15, 18, 30), (9, 10, 9))],
    ids=["sunny grass", "snowfield", "night"],
)
def test_the_shipped_segmenter_sees_no_road_where_a_view_shows_none(sky, ground):
    """A view of sky over a featureless field (what a world model that lost its road draws) must
    score no road: the metric may not fill in a road from where roads usually are."""
    views = np.empty((6, 64, 112, 3), np.uint8)
    views[:, :28], views[:, 28:] = sky, ground
    predicted = load_default_segmenter().predict(views)
    assert np.mean(predicted == ROAD) < 0.01
    assert np.mean(predicted == MARKING) < 0.01
