"""Judge protocol pieces: crop projection and size filter, cross-view grouping, description
parsing, yes-frequency aggregation per question and category."""

import numpy as np
import pytest

from world_model.eval.crops import CropConfig, ObjectCrop, crop_boxes, extract_crops, group_by_track_time
from world_model.eval.text import parse_description
from world_model.scene import CATEGORY_SIZES, Box3D, EgoState, MapGeometry, SceneFrame, SceneObject
from world_model.sensors import default_rig
from world_model.sim import ProceduralSimulator


def _car(tid: str, x: float, y: float = 0.0) -> SceneObject:
    size = CATEGORY_SIZES["car"]
    return SceneObject(tid, "car", Box3D((x, y, size[2] / 2), size, 0.0), (200, 30, 30), "red", "a red sedan")


def _frame(objects) -> SceneFrame:
    return SceneFrame(0.0, 0, EgoState(0.0, 0.0, 0.0), tuple(objects), MapGeometry(), rig=default_rig())


def test_threshold_scales_the_papers_100px_at_424_rows():
    assert CropConfig().threshold(424) == pytest.approx(100.0)
    assert CropConfig().threshold(64) == pytest.approx(100.0 * 64 / 424)
    assert CropConfig(min_side_px=7).threshold(64) == 7


def test_near_object_kept_far_object_dropped():
    sim = ProceduralSimulator()
    frame = _frame([_car("near", 7.0, 3.0), _car("far", 60.0, -3.0)])
    kept = crop_boxes(frame, sim)
    tracks = {tid for _, tid, _ in kept}
    assert "near" in tracks and "far" not in tracks
    # The far car does project into the front view: only the size filter dropped it.
    assert "far" in sim.object_boxes_2d(frame, 1)
    # With a tiny threshold the far one is kept too.
    assert "far" in {tid for _, tid, _ in crop_boxes(frame, sim, CropConfig(min_side_px=1))}


def test_extract_crops_cut_the_given_images_at_the_projected_boxes():
    sim = ProceduralSimulator()
    frame = _frame([_car("near", 7.0, 3.0)])
    cams = sim.render_cameras(frame)
    crops = extract_crops(frame, cams, sim)
    assert crops and all(c.track_id == "near" and c.category == "car" for c in crops)
    for c in crops:
        x0, y0, x1, y1 = c.box
        np.testing.assert_array_equal(c.image, cams[c.view, y0:y1, x0:x1])
    with pytest.raises(ValueError, match="cameras must be uint8"):
        extract_crops(frame, cams[:3], sim)


def test_occluded_object_is_dropped_by_visibility():
    sim = ProceduralSimulator()
    frame = _frame([_car("front", 6.0), _car("hidden", 9.0)])  # straight behind the first one
    tracks = {tid for _, tid, _ in crop_boxes(frame, sim, CropConfig(min_side_px=1))}
    assert "front" in tracks and "hidden" not in tracks
    loose = CropConfig(min_side_px=1, min_visible_fraction=0.0)
    assert "hidden" in {tid for _, tid, _ in crop_boxes(frame, sim, loose)}


def _crop(tid: str, view: int, frame: int) -> ObjectCrop:
    return ObjectCrop(tid, view, frame, "car", "red", "", (0, 0, 1, 1), np.zeros((1, 1, 3), np.uint8))


def test_cross_view_groups_by_track_and_time():
    crops = [_crop("a", 2, 0), _crop("a", 1, 0), _crop("a", 1, 5), _crop("b", 3, 0), _crop("b", 4, 0)]
    groups = group_by_track_time(crops)
    assert set(groups) == {("a", 0), ("b", 0)}  # ("a", 5) is seen in one view only
    assert [c.view for c in groups[("a", 0)]] == [1, 2]


def test_description_parsing_prefers_specific_phrases():
    assert parse_description("a dark red hatchback") == parse_description("A Dark-Red Hatchback!")
    p = parse_description("a navy truck hauling a load of trees")
    assert (p.category, p.color) == ("tree_truck", "navy")
    p = parse_description("an orange cement mixer truck")
    assert (p.category, p.color) == ("cement_mixer", "orange")
    assert parse_description("a black coach").category == "bus"
    assert parse_description("something odd").empty
