"""Object crops ("image descriptions") and 2D boxes: visible objects get one, hidden ones none."""

import numpy as np
import pytest

from world_model import Box3D, CameraRig, EgoState, SceneFrame, SceneObject, default_rig
from world_model.sim import ProceduralSimulator
from world_model.sim.demo import straight_road

ROAD = straight_road(num_lanes=3)


def obj(track_id, x, y, category="car", size=(4.5, 1.9, 1.6), color=(200, 30, 30)):
    return SceneObject(track_id=track_id, category=category, box=Box3D((x, y, size[2] / 2), size, 0.0), color=color)


def frame(objects, rig=None):
    return SceneFrame(
        time=0.0,
        frame_index=0,
        ego=EgoState(0.0, -4.0, 0.0),
        objects=tuple(objects),
        map=ROAD,
        rig=rig or default_rig(width=224, height=128),
    )


def test_visible_object_gets_a_crop_and_occluded_one_none():
    bus = obj("bus", 14.0, -4.0, "bus", (11.5, 2.6, 3.2), color=(35, 75, 200))
    hidden = obj("hidden", 30.0, -4.0, color=(40, 150, 60))  # straight behind the bus
    side = obj("side", 12.0, 0.0, color=(200, 30, 30))
    fr = frame([bus, hidden, side])
    sim = ProceduralSimulator()
    crops = sim.object_crops(fr)
    assert set(crops) == {"bus", "side"}
    for crop in crops.values():
        assert crop.dtype == np.uint8 and crop.ndim == 3 and crop.shape[2] == 3 and min(crop.shape[:2]) >= 4
    # Crops show the object's colour: the red car's crop is red-dominated, the bus's blue.
    r, g, b = crops["side"].reshape(-1, 3).mean(0)
    assert r > g + 20 and r > b + 20
    r, g, b = crops["bus"].reshape(-1, 3).mean(0)
    assert b > r + 20
    # Without the bus, the hidden car is visible and gets a crop.
    assert "hidden" in sim.object_crops(frame([hidden, side]))


def test_out_of_view_object_gets_no_crop_and_no_box():
    front_only = CameraRig(cameras=(default_rig(width=224, height=128).cameras[1],))
    ahead, behind = obj("ahead", 15.0, -4.0), obj("behind", -15.0, -4.0)
    fr = frame([ahead, behind], rig=front_only)
    sim = ProceduralSimulator()
    assert set(sim.object_crops(fr)) == {"ahead"}
    boxes = sim.object_boxes_2d(fr, 0)
    assert set(boxes) == {"ahead"}
    x0, y0, x1, y1 = boxes["ahead"]
    assert 0 <= x0 < x1 <= 224 and 0 <= y0 < y1 <= 128
    assert x0 < 112 < x1  # straight ahead: around the image centre


def test_crop_uses_the_given_cameras_and_checks_their_shape():
    fr = frame([obj("a", 12.0, -4.0)])
    sim = ProceduralSimulator()
    cams = np.zeros((6, 128, 224, 3), dtype=np.uint8)
    crop = sim.object_crops(fr, cams)["a"]
    assert not crop.any()  # cut from the provided (black) images
    with pytest.raises(ValueError, match="cameras must be"):
        sim.object_crops(fr, cams[:, :64])
