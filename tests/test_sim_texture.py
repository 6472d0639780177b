"""The lazily tiled road texture and the painter's occlusion order."""

import numpy as np

from world_model import Box3D, EgoState, LaneLine, MapGeometry, SceneFrame, SceneObject, default_rig
from world_model.sim import ProceduralSimulator, SimConfig
from world_model.sim.demo import ring_road, straight_road
from world_model.sim.texture import MapTexture, labels_layout

CFG = SimConfig()
OFF0, ROAD0, MARKING, EDGE = labels_layout(CFG.texture_noise_levels)


def classify(labels):
    return np.where(labels >= MARKING, labels, np.where(labels >= ROAD0, ROAD0, OFF0))


def test_labels_on_a_10km_highway_and_far_off_the_map():
    road = straight_road(num_lanes=4, x0=0.0, x1=10_000.0)  # lanes centred at y = 0, -4, -8, -12
    tex = MapTexture(road, CFG)
    xs = np.array([5.0, 4_000.0, 9_990.0, 5_000.0, 5_000.0, 5_000.0, -3_000.0, 5_000.0])
    ys = np.array([0.0, -8.0, -12.0, 2.0, -14.0, 40.0, 0.0, 1e6])
    got = classify(tex.lookup(xs, ys))
    assert got.tolist() == [ROAD0, ROAD0, ROAD0, EDGE, EDGE, OFF0, OFF0, OFF0]
    assert tex.tiles_drawn <= 8  # only the tiles that were looked at, plus the shared off-road tile


def test_dashed_lines_alternate_and_tile_memory_is_bounded():
    line = LaneLine(points=np.array([[0.0, -2.0], [300.0, -2.0]]), kind="dashed")
    road = MapGeometry(lane_lines=(line,))
    cfg = SimConfig(texture_max_tiles=4, dash_length_m=3.0, dash_gap_m=6.0)
    tex = MapTexture(road, cfg)
    xs = np.arange(0.5, 290.0, 1.0)
    painted = tex.lookup(xs, np.full_like(xs, -2.0)) == MARKING
    period = (xs % 9.0) < 3.0  # 3 m dash, 6 m gap from the line's start
    assert np.array_equal(painted, period)
    assert tex.tiles_drawn > 4  # one lookup needs 12 tiles along 300 m: they all fit, then ...
    far = tex.lookup(np.array([1.0]), np.array([60.0]))  # ... the next miss restarts the atlas
    assert OFF0 <= far[0] < ROAD0 and tex.tiles_drawn == 1
    again = tex.lookup(xs, np.full_like(xs, -2.0)) == MARKING
    assert np.array_equal(again, painted)


def test_rollouts_on_equal_roads_share_one_texture(monkeypatch):
    import world_model.sim.simulator as simulator

    built = []

    class CountedTexture(MapTexture):
        def __init__(self, *args, **kwargs):
            built.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(simulator, "MapTexture", CountedTexture)
    a, b = straight_road(num_lanes=3), straight_road(num_lanes=3)  # equal content, two objects
    other = straight_road(num_lanes=2)
    assert a is not b and a.digest == b.digest and other.digest != a.digest
    moved = MapGeometry(lane_lines=(LaneLine(points=a.lane_lines[0].points + 0.01, kind=a.lane_lines[0].kind),))
    assert moved.digest != MapGeometry(lane_lines=a.lane_lines[:1]).digest
    sim = ProceduralSimulator(config=SimConfig(texture_cache_size=1))
    images = []
    for road in (a, b, a, b):
        frame = SceneFrame(time=0.0, frame_index=0, ego=EgoState(x=20.0, y=0.0, yaw=0.0), objects=(), map=road)
        images.append(sim.render_cameras(frame))
    assert len(built) == 1  # one road, one texture, however many map objects draw it
    assert all(np.array_equal(images[0], im) for im in images[1:])


def test_ring_road_is_drivable_on_the_ring_only():
    tex = MapTexture(ring_road(radius=30.0, num_lanes=2), CFG)
    ang = np.linspace(0, 2 * np.pi, 37)
    on = classify(tex.lookup(36.0 * np.cos(ang), 36.0 * np.sin(ang)))
    inside = classify(tex.lookup(20.0 * np.cos(ang), 20.0 * np.sin(ang)))
    assert np.all(on == ROAD0) and np.all(inside == OFF0)


def _frame(objects):
    return SceneFrame(
        time=0.0,
        frame_index=0,
        ego=EgoState(0.0, -4.0, 0.0),
        objects=tuple(objects),
        map=straight_road(num_lanes=3),
        rig=default_rig(width=224, height=128),
    )


def test_near_object_occludes_far_one_regardless_of_order():
    red = SceneObject("near", "car", Box3D((12.0, -4.0, 0.8), (4.5, 1.9, 1.6), 0.0), color=(200, 30, 30))
    blue = SceneObject("far", "bus", Box3D((30.0, -4.0, 1.6), (11.5, 2.6, 3.2), 0.0), color=(35, 75, 200))
    sim = ProceduralSimulator()
    a = sim.render_cameras(_frame([red, blue]))
    b = sim.render_cameras(_frame([blue, red]))
    assert np.array_equal(a, b)
    ((x0, y0, x1, y1),) = sim.object_boxes_2d(_frame([red]), 1).values()
    r, g, bl = a[1, (y0 + y1) // 2 + 2, (x0 + x1) // 2].astype(int)  # rear of the red car, below its window
    assert r > bl + 40
    # The bus shows above the car (it is taller and behind it): blue pixels above the car's box.
    above = a[1, :y0, x0:x1].astype(int)
    assert ((above[..., 2] > above[..., 0] + 60) & (above[..., 2] > above[..., 1] + 30)).sum() > 20
