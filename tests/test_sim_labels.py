"""Per-camera label maps: sky, road texture classes and objects after occlusion, at any resolution."""

from dataclasses import replace

import numpy as np
import pytest

from world_model import Box3D, EgoState, SceneFrame, SceneObject, ScenePrompt, default_rig
from world_model.raster.classes import (
    CLASS_PLANE,
    LABEL_CLASSES,
    MAP_PLANES,
    MARKING,
    OFFROAD,
    OTHER_OBJECT,
    PAINT_BITS,
    PAINT_PLANE,
    ROAD,
    SKY,
    SURFACE_PLANE,
    SURFACE_STEPS,
    VEHICLE,
    VULNERABLE,
    decode_paint,
    decode_surface,
    encode_paint,
    encode_surface,
)
from world_model.sim import ProceduralSimulator, ground
from world_model.sim.config import SimConfig
from world_model.sim.demo import demo_frame, straight_road
from world_model.sim.labels import LabelRasterizer, label_maps, scaled_rig

ROAD_MAP = straight_road(num_lanes=3)  # lanes centred at y = 0, -4, -8; road spans y in [-10, 2]
RIG = default_rig(width=112, height=64)
FRONT = 1  # view order of the default rig: front-left, front, front-right, ...


def frame(objects=()):
    ego = EgoState(0.0, -4.0, 0.0)
    return SceneFrame(time=0.0, frame_index=0, ego=ego, objects=tuple(objects), map=ROAD_MAP, rig=RIG)


def obj(track_id, x, y, category, size):
    box = Box3D((x, y, size[2] / 2), size, 0.0)
    return SceneObject(track_id=track_id, category=category, box=box, color=(90, 90, 90))


def test_background_classes_follow_the_road_geometry():
    fr = frame()
    labels = label_maps(fr, RIG, 64, 112)
    assert labels.shape == (6, 64, 112) and labels.dtype == np.uint8
    rays = ground.ground_rays(RIG, fr.lidar.mount_height, SimConfig().max_ground_distance_m)
    flat = labels.reshape(-1)
    sky = np.ones(flat.size, dtype=bool)
    sky[rays.ground_index] = False
    assert np.all(flat[sky] == SKY) and np.all(flat[~sky] != SKY)
    # Ground hits in world y (ego at y = -4 facing +x, so world y = ego-frame y - 4).
    wy = rays.ground_xy[:, 0, 1].astype(np.float64) - 4.0
    hit = flat[rays.ground_index]
    inside = np.abs(wy - (-4.0)) < 5.5  # well inside the road, away from its edges
    outside = np.abs(wy - (-4.0)) > 6.5
    assert np.all(np.isin(hit[inside], (ROAD, MARKING))) and np.mean(hit[inside] == ROAD) > 0.8
    assert np.all(hit[outside] == OFFROAD)
    # Lane lines at y = -2 and -6 are painted: markings appear only near a line.
    near_line = np.min(np.abs(wy[:, None] - np.array([2.0, -2.0, -6.0, -10.0])), axis=1) < 0.5
    assert np.any(hit == MARKING) and np.all(near_line[hit == MARKING])


def test_objects_take_their_class_after_occlusion():
    car = obj("car", 15.0, -4.0, "car", (4.5, 1.9, 1.6))
    hidden = obj("walker", 30.0, -4.0, "pedestrian", (0.6, 0.6, 1.2))  # behind the car
    walker = obj("walker2", 12.0, 3.5, "pedestrian", (0.6, 0.6, 1.8))
    cone = obj("cone", 10.0, -9.0, "cone", (0.4, 0.4, 0.7))
    fr = frame([car, hidden, walker, cone])
    labels = label_maps(fr, RIG, 64, 112)
    seen, _ = ProceduralSimulator().object_masks(fr)
    assert np.array_equal(np.isin(labels, (VEHICLE, VULNERABLE, OTHER_OBJECT)), seen)
    front = labels[FRONT]
    assert front[36, 56] == VEHICLE  # the car straight ahead, just below the horizon
    assert np.any(front == VULNERABLE) and np.any(front == OTHER_OBJECT)
    visible, _ = ProceduralSimulator().visible_pixels(fr)
    assert visible[FRONT, 1] == 0  # the hidden pedestrian contributes nothing
    assert np.sum(front == VULNERABLE) == visible[FRONT, 2]


def test_lower_resolution_matches_downsampled_full_resolution():
    fr = demo_frame(num_objects=12, seed=3, rig=RIG)
    full = label_maps(fr, RIG, 64, 112)
    small = label_maps(fr, RIG, 16, 28)
    assert small.shape == (6, 16, 28)
    centres = full[:, 2::4, 2::4]  # the full-resolution pixel nearest each small pixel's centre
    assert np.mean(small == centres) > 0.9
    for c in (SKY, ROAD, VEHICLE):
        assert np.any(small == c)


def test_rasterizer_reuse_is_identical_and_deterministic():
    road = straight_road()
    # two object sets, interleaved: the cached meshes must follow each frame's objects
    frames = [
        demo_frame(num_objects=18 if i % 2 else 7, seed=1, rig=RIG, road=road, frame_index=i, ego_x=3.0 * i)
        for i in range(4)
    ]
    r = LabelRasterizer()
    again = [r(f, RIG, 32, 56) for f in frames]
    fresh = [label_maps(f, RIG, 32, 56) for f in frames]
    for a, b in zip(again, fresh, strict=True):
        assert np.array_equal(a, b)
    assert int(max(a.max() for a in again)) < len(LABEL_CLASSES)


def test_bad_size_is_rejected():
    with pytest.raises(ValueError, match="height=0"):
        scaled_rig(RIG, 0, 10)


def test_paint_round_trips_each_channel_to_its_high_bits():
    rgb = np.array([[0, 0, 0], [255, 255, 255], [200, 30, 30], [0, 0, 128], [139, 0, 0]], dtype=np.uint8)
    back = decode_paint(encode_paint(rgb))
    assert back.shape == (5, 3) and back.dtype == np.float32
    levels = np.array([(1 << b) - 1 for b in PAINT_BITS])
    assert np.array_equal(np.rint(back * levels).astype(int), rgb.astype(int) >> (8 - np.array(PAINT_BITS)))
    assert np.array_equal(back[0], [0, 0, 0]) and np.array_equal(back[1], [1, 1, 1])
    assert back[2, 0] > 0.7 and back[2, 1:].max() < 0.2  # red stays red
    assert back[3, 2] > 0.3 and back[3, :2].max() == 0  # navy stays blue
    all_bytes = np.arange(256, dtype=np.uint8)
    assert np.array_equal(encode_paint(np.rint(decode_paint(all_bytes) * 255).astype(np.uint8)), all_bytes)


def test_the_paint_plane_holds_each_visible_faces_unlit_paint_and_nothing_elsewhere():
    red = SceneObject("red", "car", Box3D((15.0, -4.0, 0.8), (4.5, 1.9, 1.6), 0.0), color=(200, 20, 20))
    blue = SceneObject("blue", "car", Box3D((15.0, -4.0, 0.8), (4.5, 1.9, 1.6), 0.0), color=(20, 40, 200))
    for car in (red, blue):
        fr = frame([car])
        maps = LabelRasterizer().maps(fr, RIG, 64, 112)
        assert maps.shape == (6, MAP_PLANES, 64, 112) and maps.dtype == np.uint8
        classes, paint = maps[:, CLASS_PLANE], maps[:, PAINT_PLANE]
        assert np.array_equal(classes, label_maps(fr, RIG, 64, 112))  # the class plane is the label map
        assert np.all(paint[classes != VEHICLE] == 0)
        on_car = paint[classes == VEHICLE]
        values, counts = np.unique(on_car, return_counts=True)
        assert values[np.argmax(counts)] == encode_paint(np.array(car.color))  # the body, most of the car
        assert len(values) > 1  # its glass and tyres have their own paint
    # The paint is unlit: a night scene paints the car as the day does, where the images darken.
    night = replace(frame([red]), prompt=ScenePrompt(time_of_day="night"))
    raster = LabelRasterizer()
    assert np.array_equal(raster.maps(night, RIG, 64, 112), raster.maps(frame([red]), RIG, 64, 112))


def test_surface_bytes_round_trip_and_keep_zero_for_no_surface():
    v = np.linspace(-1.0, 1.0, 9)
    back = decode_surface(encode_surface(v))
    assert np.abs(back - v).max() <= 1.0 / SURFACE_STEPS + 1e-6
    assert encode_surface(v).min() >= 1 and decode_surface(np.zeros(3, np.uint8)).tolist() == [0.0, 0.0, 0.0]


def test_the_surface_plane_is_where_the_rendered_ground_is_brighter_or_darker():
    car = obj("car", 12.0, -4.0, "car", (4.5, 1.9, 1.6))
    fr = frame([car])
    maps = LabelRasterizer().maps(fr, RIG, 64, 112)
    classes, surface = maps[:, CLASS_PLANE], maps[:, SURFACE_PLANE]
    # a textured surface (road, off-road) has a surface byte; the sky, markings and objects none
    assert np.all((surface > 0) == np.isin(classes, (ROAD, OFFROAD)))
    variation = decode_surface(surface)
    assert variation.min() < -0.5 and variation.max() > 0.5  # the patches span the palette's range
    # The rendered road is brighter where the plane says so (same light, same distances on average).
    image = ProceduralSimulator().render(fr).cameras.astype(np.float64).mean(-1)
    road = classes == ROAD
    bright, dark = image[road & (variation > 0.5)].mean(), image[road & (variation < -0.5)].mean()
    assert bright > dark * 1.1
    # Moving the ego a few metres moves the patches with the ground: the plane changes, the classes hardly.
    moved = replace(fr, ego=EgoState(3.0, -4.0, 0.0))
    again = LabelRasterizer().maps(moved, RIG, 64, 112)
    assert np.mean(again[:, SURFACE_PLANE] != surface) > 0.3
