"""Cameras of the procedural simulator: projection, placement, determinism, weather and time."""

import dataclasses

import numpy as np
import pytest

from world_model import Box3D, EgoState, SceneFrame, SceneObject, ScenePrompt, default_rig
from world_model.sim import ProceduralSimulator, SimConfig, mosaic
from world_model.sim.demo import demo_frame, straight_road

ROAD = straight_road(num_lanes=3)
FRONT, BACK = 1, 4


def frame(objects=(), weather="sunny", time_of_day="day", rig=None, ego_y=-4.0, index=0):
    return SceneFrame(
        time=0.0,
        frame_index=index,
        ego=EgoState(x=0.0, y=ego_y, yaw=0.0),
        objects=tuple(objects),
        map=ROAD,
        prompt=ScenePrompt("test road", weather, time_of_day),
        rig=rig or default_rig(),
        scenario="unit",
    )


def car(x, y, color=(200, 30, 30), track_id="car", category="car", yaw=0.0, size=(4.5, 1.9, 1.6)):
    return SceneObject(track_id=track_id, category=category, box=Box3D((x, y, size[2] / 2), size, yaw), color=color)


def test_point_projects_to_hand_computed_pixel():
    fr = frame()
    cam = fr.rig.cameras[FRONT]
    p = np.array([[20.0, 3.0, -1.0]])  # LiDAR frame: 20 m ahead, 3 m left, 1 m down
    # By hand: camera axes x right (= -y_lidar), y down (= -z_lidar), z forward (= x_lidar).
    rel = p[0] - cam.t
    xc, yc, zc = -rel[1], -rel[2], rel[0]
    expected = (cam.K[0, 0] * xc / zc + cam.K[0, 2], cam.K[1, 1] * yc / zc + cam.K[1, 2])
    uv, depth = ProceduralSimulator().project(fr, FRONT, p)
    assert depth[0] == pytest.approx(zc)
    assert uv[0] == pytest.approx(expected)
    assert uv[0, 0] < cam.width / 2  # to the left of the image centre
    uv_back, depth_back = ProceduralSimulator().project(fr, BACK, p)
    assert depth_back[0] < 0 and np.isnan(uv_back).all()


def _forward_camera():
    """Looks along LiDAR +x from the origin: camera x = -y_lidar, y = -z_lidar, z = x_lidar."""
    from world_model.sensors import CameraSpec

    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera -> LiDAR
    return CameraSpec("test", K, R, np.zeros(3), width=100, height=80)


def _aabb(x, y, z):
    """(8, 3) corners of the axis-aligned box spanning the (lo, hi) ranges x, y, z."""
    return np.array([(a, b, c) for a in x for b in y for c in z], dtype=float)


def test_box_extent_hand_worked():
    """u = 100 * (-y) / x + 50, v = 100 * (-z) / x + 40, worked out by hand per case."""
    cam = _forward_camera()
    # 10-12 m ahead, 2 m wide, 1 m tall: the near face bounds it, u in [40, 60], v in [35, 45].
    assert cam.box_extent(_aabb((10, 12), (-1, 1), (-0.5, 0.5)), near=0.5) == (40, 35, 60, 45)
    # Off-centre and fractional (floor/ceil): u in [50 - 300/8, 50 - 200/9] = [12.5, 27.8] (the
    # far face bounds the right side), v in [40 - 30/8, 40] = [36.25, 40].
    assert cam.box_extent(_aabb((8, 9), (2, 3), (0, 0.3)), near=0.5) == (12, 36, 28, 40)
    # Straddling the camera: edges are clipped at x = near = 1, where the box spans u in [-50, 150]
    # and v in [-10, 90]; clipped to the 100 x 80 image.
    assert cam.box_extent(_aabb((-2, 4), (-1, 1), (-0.5, 0.5)), near=1.0) == (0, 0, 100, 80)
    # Behind the camera, or in front but outside the image: no extent.
    assert cam.box_extent(_aabb((-6, -4), (-1, 1), (-0.5, 0.5)), near=0.5) is None
    assert cam.box_extent(_aabb((5, 6), (20, 22), (-0.5, 0.5)), near=0.5) is None


def test_object_in_left_lane_appears_left_in_front_and_not_in_back():
    sim = ProceduralSimulator()
    empty = sim.render_cameras(frame())
    with_car = sim.render_cameras(frame([car(15.0, 0.0)]))  # ego at y = -4: the car is 4 m to its left
    diff = np.abs(with_car.astype(int) - empty.astype(int)).sum(-1) > 30
    w = diff.shape[2]
    front = diff[FRONT]
    assert front[:, : w // 2].sum() > 50
    assert front[:, : w // 2].sum() > 10 * front[:, w // 2 :].sum()
    assert diff[BACK].sum() == 0
    assert sim.object_boxes_2d(frame([car(15.0, 0.0)]), BACK) == {}
    ((x0, _, x1, _),) = sim.object_boxes_2d(frame([car(15.0, 0.0)]), FRONT).values()
    assert x1 <= w // 2 + 1 and x0 < x1


def test_same_frame_renders_identically_even_with_other_thread_counts():
    import cv2

    fr = demo_frame(weather="rain", time_of_day="night")
    a = ProceduralSimulator().render(fr)
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        b = ProceduralSimulator().render(fr)
    finally:
        cv2.setNumThreads(threads)
    assert np.array_equal(a.cameras, b.cameras) and np.array_equal(a.lidar, b.lidar)
    assert np.array_equal(a.bev, b.bev)
    # Rain streaks are seeded from the frame: a different frame index moves them.
    c = ProceduralSimulator().render_cameras(dataclasses.replace(fr, frame_index=fr.frame_index + 1))
    assert not np.array_equal(a.cameras, c)


def test_renders_at_224x400_with_all_categories():
    rig = default_rig(width=400, height=224)
    fr = demo_frame(rig=rig, num_objects=22)
    obs = ProceduralSimulator().render(fr)
    assert obs.cameras.shape == (6, 224, 400, 3) and obs.cameras.dtype == np.uint8
    assert obs.cameras.std() > 10
    m = mosaic(obs, fr)
    assert m.dtype == np.uint8 and m.ndim == 3 and m.shape[1] > 3 * 400
    # The ring layout puts FRONT in the top middle and BACK in the bottom middle.
    assert np.array_equal(m[:224, 400:800], obs.cameras[1]) and np.array_equal(m[224:448, 400:800], obs.cameras[4])
    # With the frame, object boxes and the ego are drawn on the BEV panel.
    assert (mosaic(obs) != m).any()


def test_night_is_darker_than_day_and_lamps_glow():
    sim = ProceduralSimulator()
    objs = [car(12.0, -4.0, color=(128, 128, 132), yaw=np.pi, track_id="oncoming")]  # facing the ego
    day = sim.render_cameras(frame(objs))
    night = sim.render_cameras(frame(objs, time_of_day="night"))
    assert night.mean() < 0.5 * day.mean()
    # The oncoming car's headlights are the brightest thing in the night FRONT view.
    ((x0, y0, x1, y1),) = sim.object_boxes_2d(frame(objs), FRONT).values()
    assert night[FRONT, y0:y1, x0:x1].max() > 200


def test_fog_lowers_contrast_at_distance():
    sim = ProceduralSimulator()
    far = [car(45.0, -4.0, color=(25, 25, 28))]
    contrast = {}
    for weather in ("sunny", "fog"):
        with_car = sim.render_cameras(frame(far, weather=weather))[FRONT].astype(float)
        without = sim.render_cameras(frame(weather=weather))[FRONT].astype(float)
        contrast[weather] = np.abs(with_car - without).sum(-1).max()
    assert contrast["fog"] < 0.5 * contrast["sunny"]


def test_weather_changes_the_image():
    sim = ProceduralSimulator()
    images = {w: sim.render_cameras(frame(weather=w)) for w in ("sunny", "cloudy", "rain", "fog", "snow")}
    names = list(images)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert np.abs(images[a].astype(int) - images[b].astype(int)).mean() > 3, (a, b)


def test_object_straddling_the_camera_is_clipped_not_crashing():
    sim = ProceduralSimulator()
    bus = car(0.0, 0.0, category="bus", size=(11.5, 2.6, 3.2), track_id="bus")  # alongside, left
    cams = sim.render_cameras(frame([bus]))
    empty = sim.render_cameras(frame())
    left_views = (0, 5)  # FRONT_LEFT, BACK_LEFT see it at close range
    for v in left_views:
        assert (np.abs(cams[v].astype(int) - empty[v].astype(int)).sum(-1) > 30).mean() > 0.2


def test_bad_input_is_rejected_with_specific_errors():
    sim = ProceduralSimulator()
    with pytest.raises(ValueError, match="unknown object category"):
        sim.render_cameras(frame([car(10, 0, category="spaceship")]))
    with pytest.raises(ValueError, match="finite"):
        sim.render_cameras(dataclasses.replace(frame(), ego=EgoState(x=float("nan"), y=0.0, yaw=0.0)))
    with pytest.raises(IndexError):
        sim.project(frame(), 6, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="shape"):
        sim.project(frame(), 0, np.zeros((3,)))
    with pytest.raises(ValueError):
        SimConfig(near_plane_m=0.0)


def test_simulator_does_not_import_gym_or_highway_env():
    import subprocess
    import sys

    code = (
        "import sys, world_model.sim; "
        "bad = [m for m in ('gymnasium', 'highway_env', 'torch') if m in sys.modules]; "
        "sys.exit(1 if bad else 0)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
