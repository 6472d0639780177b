"""LiDAR range map of the procedural simulator: exact box ranges and row/column conventions."""

import numpy as np
import pytest

from world_model import Box3D, EgoState, LidarSpec, SceneFrame, SceneObject
from world_model.sim import ProceduralSimulator
from world_model.sim.demo import straight_road

ROAD = straight_road(num_lanes=3)
SPEC = LidarSpec()
BUS = (11.5, 2.6, 3.2)  # taller than the LiDAR mount: the level beams hit it


def frame(objects=(), ego=(0.0, -4.0, 0.0), lidar=SPEC):
    return SceneFrame(
        time=0.0,
        frame_index=0,
        ego=EgoState(*ego),
        objects=tuple(objects),
        map=ROAD,
        lidar=lidar,
    )


def box(x, y, size=(4.5, 1.9, 1.6), yaw=0.0, track_id="o", category="car"):
    return SceneObject(track_id=track_id, category=category, box=Box3D((x, y, size[2] / 2), size, yaw))


def changed_columns(with_obj, empty):
    return np.nonzero((with_obj != empty).any(axis=0))[0]


@pytest.mark.parametrize("d, size", [(20.0, (4.5, 1.9, 1.6)), (35.0, (8.5, 2.5, 3.4)), (9.0, (0.6, 0.6, 1.75))])
def test_object_straight_ahead_reads_d_minus_half_length(d, size):
    sim = ProceduralSimulator()
    ranges = sim.render_lidar(frame([box(d, -4.0, size)]))
    assert ranges.shape == (SPEC.beams, SPEC.azimuth) and ranges.dtype == np.float32
    col = SPEC.azimuth // 2  # azimuth 0 = straight ahead
    el = SPEC.elevations()
    face = d - size[0] / 2
    # Beams that reach the rear face between the road and the box top, by hand.
    z_at_face = face * np.tan(el)
    expected = (z_at_face >= -SPEC.mount_height) & (z_at_face <= -SPEC.mount_height + size[2])
    hits = np.abs(ranges[:, col] * np.cos(el) - face) < 0.1
    assert expected.any()
    assert np.array_equal(hits, expected)
    level = np.abs(el) < np.deg2rad(1.0)  # near-horizontal beams: the range itself is d - l/2
    assert np.all(np.abs(ranges[level & expected, col] - face) < 0.1)


def test_column_and_row_conventions():
    sim = ProceduralSimulator()
    empty = sim.render_lidar(frame())
    a = SPEC.azimuth
    # Ground returns only in the beams that look down, nearest in the bottom row; sky rows read 0.0.
    el = SPEC.elevations()
    assert np.all(empty[el >= 0] == 0.0)
    assert empty[-1, 0] == pytest.approx(SPEC.mount_height / np.sin(np.deg2rad(30.0)), rel=1e-5)
    down_in_range = (el < 0) & (SPEC.mount_height / np.sin(np.abs(el)) <= SPEC.max_range)
    assert np.all(empty[down_in_range] > 0) and np.all(empty[(el < 0) & ~down_in_range] == 0.0)
    assert np.all(np.diff(empty[down_in_range, 0]) < 0)  # lower rows hit the road nearer
    # An object at +90 deg (ego's left) shows up around column azimuth / 4, at -90 deg around 3/4.
    for y_off, expected_col in ((10.0, a // 4), (-10.0, 3 * a // 4)):
        cols = changed_columns(sim.render_lidar(frame([box(0.0, -4.0 + y_off, yaw=0.0)])), empty)
        assert abs(np.median(cols) - expected_col) <= 2
    # Straight behind wraps around: columns at both ends of the range map.
    cols = changed_columns(sim.render_lidar(frame([box(-15.0, -4.0)])), empty)
    assert cols.min() == 0 and cols.max() == a - 1


def test_ego_heading_rotates_the_scan():
    sim = ProceduralSimulator()
    # Ego heading +y in the world: an object at world +y is straight ahead.
    ranges = sim.render_lidar(frame([box(0.0, 16.0, size=BUS, yaw=np.pi / 2)], ego=(0.0, -4.0, np.pi / 2)))
    col = SPEC.azimuth // 2
    level = np.argmin(np.abs(SPEC.elevations()))
    assert ranges[level, col] == pytest.approx(20.0 - BUS[0] / 2, abs=0.1)


def test_max_range_and_no_return():
    sim = ProceduralSimulator()
    spec = LidarSpec(max_range=30.0, beams=8, azimuth=256)
    far = sim.render_lidar(frame([box(45.0, -4.0)], lidar=spec))
    assert far.shape == (8, 256)
    assert far.max() <= 30.0
    assert np.array_equal(far, sim.render_lidar(frame(lidar=spec)))  # the far car is out of range
    near = sim.render_lidar(frame([box(20.0, -4.0)], lidar=spec))
    assert (near != far).any()


def test_occlusion_keeps_the_nearest_return():
    sim = ProceduralSimulator()
    col = SPEC.azimuth // 2
    level = np.argmin(np.abs(SPEC.elevations()))
    objs = [box(40.0, -4.0, BUS, track_id="far"), box(20.0, -4.0, BUS, track_id="near")]
    both = sim.render_lidar(frame(objs))
    assert both[level, col] == pytest.approx(20.0 - BUS[0] / 2, abs=0.1)
    assert np.array_equal(both, sim.render_lidar(frame(objs[::-1])))  # object order does not matter


def brute_force_ranges(frame_, spec):
    """Every ray against every box, no culling: the reference for the simulator's culled cast."""
    dirs = spec.ray_directions().reshape(-1, 3)
    best = np.full(len(dirs), np.inf)
    el = spec.elevations()
    ground = np.where(el < 0, spec.mount_height / np.sin(np.maximum(-el, 1e-9)), np.inf)
    best = np.minimum(best, np.repeat(ground, spec.azimuth))
    for b in frame_.object_boxes_lidar():
        c, s = np.cos(b.yaw), np.sin(b.yaw)
        rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])  # LiDAR -> box frame
        o = rot @ (-np.asarray(b.center))
        d = dirs @ rot.T
        half = np.asarray(b.size) / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_near > 0)
        best[hit] = np.minimum(best[hit], t_near[hit])
    best[best > spec.max_range] = spec.no_return
    return best.reshape(spec.beams, spec.azimuth)


def test_culled_cast_matches_brute_force_for_random_boxes():
    rng = np.random.default_rng(7)
    objs = []
    for i in range(12):
        size = (rng.uniform(0.4, 12.0), rng.uniform(0.4, 3.0), rng.uniform(0.5, 4.0))
        x, y = rng.uniform(-40, 40), rng.uniform(-25, 25)
        if abs(x) < 4 and abs(y + 4) < 4:
            x += 10.0
        objs.append(box(x, y, size, yaw=rng.uniform(-np.pi, np.pi), track_id=str(i)))
    fr = frame(objs, ego=(1.0, -4.0, 0.4))
    got = ProceduralSimulator().render_lidar(fr)
    ref = brute_force_ranges(fr, SPEC)
    assert np.allclose(got, ref, atol=1e-3)
    assert (got != ProceduralSimulator().render_lidar(frame(ego=(1.0, -4.0, 0.4)))).sum() > 500
