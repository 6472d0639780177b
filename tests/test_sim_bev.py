"""BEV raster of the procedural simulator: ego-aligned, classes in spec order."""

import numpy as np
import pytest

from world_model import BevSpec, EgoState, LaneLine, MapGeometry, SceneFrame
from world_model.sim import ProceduralSimulator

SPEC = BevSpec()  # 80 x 80 cells of 1 m, 40 m each way
DRIVABLE, DIVIDER, EDGE = 0, 1, 2


def line(p0, p1, n=50):
    return np.linspace(p0, p1, n)


def frame(m, ego=(0.0, 0.0, 0.0), bev=SPEC):
    return SceneFrame(time=0.0, frame_index=0, ego=EgoState(*ego), objects=(), map=m, bev=bev)


def test_left_is_left_and_forward_is_up():
    road = MapGeometry(
        lane_lines=(LaneLine(points=line((10.0, 2.0), (30.0, 2.0)), kind="dashed"),),  # only ahead
        road_edges=(line((-100.0, 6.0), (100.0, 6.0)),),  # 6 m to the left
        drivable_area=(np.array([[-100.0, -6.0], [100.0, -6.0], [100.0, 6.0], [-100.0, 6.0]]),),
    )
    bev = ProceduralSimulator().render_bev(frame(road))
    h, w, c = SPEC.shape
    assert bev.shape == (h, w, c) == (80, 80, 3) and bev.dtype == np.uint8
    assert set(np.unique(bev)) <= {0, 1}
    edge_cols = np.nonzero(bev[..., EDGE].any(axis=0))[0]
    assert np.all(edge_cols < w // 2)  # left of the ego
    assert abs(edge_cols.mean() - (SPEC.half_width_m - 6.0) / SPEC.m_per_px) <= 1
    divider_rows = np.nonzero(bev[..., DIVIDER].any(axis=1))[0]
    assert np.all(divider_rows < h // 2)  # ahead = up
    assert divider_rows.min() == pytest.approx((SPEC.forward_m - 30.0) / SPEC.m_per_px, abs=1)
    # Drivable area spans y in [-6, 6]: the 12 central columns, all rows.
    assert bev[:, w // 2 - 5 : w // 2 + 5, DRIVABLE].all() and not bev[:, :30, DRIVABLE].any()


def test_bev_follows_the_ego_heading():
    # Facing world +y, the ego's left is world -x: an edge at world x = -6 is on the left.
    road = MapGeometry(road_edges=(line((-6.0, -100.0), (-6.0, 100.0)),))
    bev = ProceduralSimulator().render_bev(frame(road, ego=(0.0, 0.0, np.pi / 2)))
    cols = np.nonzero(bev[..., EDGE].any(axis=0))[0]
    assert len(cols) and np.all(cols < SPEC.shape[1] // 2)
    assert abs(cols.mean() - 34) <= 1


def test_unpainted_boundaries_are_not_dividers_and_custom_specs_work():
    road = MapGeometry(lane_lines=(LaneLine(points=line((-50.0, 2.0), (50.0, 2.0)), kind="none"),))
    bev = ProceduralSimulator().render_bev(frame(road))
    assert not bev.any()
    spec = BevSpec(forward_m=20.0, backward_m=10.0, half_width_m=10.0, m_per_px=0.5, classes=("road_edge",))
    road = MapGeometry(road_edges=(line((-50.0, -3.0), (50.0, -3.0)),))
    out = ProceduralSimulator(bev=spec).render_bev(frame(road))
    assert out.shape == (60, 40, 1)
    cols = np.nonzero(out[..., 0].any(axis=0))[0]
    assert np.all(cols >= 20) and abs(cols.mean() - 25.5) <= 1  # y = -3 -> (10 + 3) / 0.5 - 0.5


def test_unknown_bev_class_is_rejected():
    spec = BevSpec(classes=("drivable_area", "crosswalk"))
    with pytest.raises(ValueError, match="crosswalk"):
        ProceduralSimulator(bev=spec).render_bev(frame(MapGeometry()))
