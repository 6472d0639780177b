"""Reference conditioning: mask semantics, task masks, object-completion region, teacher expansion."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.model_fixtures import make_frames, perturbed, tiny_conditions
from world_model import Box3D, SceneObject
from world_model.model import MultiViewDiT, get_preset
from world_model.model.reference import (
    TASKS,
    ReferenceConfig,
    expand_teacher,
    object_region,
    reference_channels,
    reference_input,
    task_mask,
)
from world_model.sim import ProceduralSimulator

RCFG = ReferenceConfig()


def _frame_with_hard_objects(cfg):
    """One frame with cars ahead, plus one beside the ego (crosses side cameras' near planes)
    and one behind (its azimuth span wraps around +-180 degrees in the range map)."""
    frame = make_frames(cfg, 1, num_objects=3, seed=3)[0]
    extra = (
        SceneObject(track_id="beside", category="car", box=Box3D((0.5, 3.2, 0.8), (4.5, 1.9, 1.6), 0.0)),
        SceneObject(track_id="behind", category="truck", box=Box3D((-14.0, 0.3, 1.7), (8.5, 2.5, 3.4), 0.1)),
    )
    return frame.with_objects(frame.objects + extra)


def _cells(mask_px: np.ndarray, d: int) -> np.ndarray:
    """(H, W) bool pixels -> (H/d, W/d) bool: latent cells containing any marked pixel."""
    h, w = mask_px.shape
    return mask_px.reshape(h // d, d, w // d, d).any(axis=(1, 3))


def test_reference_input_marks_observed_regions_and_zeroes_the_rest():
    x = torch.randn(2, 3, 7, 4, 2, 4) + 5.0
    mask = torch.zeros(2, 3, 7, 1, 2, 4)
    mask[0, 0, 1] = 1.0
    mask[1, :, :, :, 0, 0] = 1.0
    extra = reference_input(x, mask)
    assert extra.shape == (2, 3, 7, 5, 2, 4)
    assert torch.equal(extra[..., -1:, :, :], mask)  # last channel is the mask
    observed = mask.expand_as(x).bool()
    assert torch.equal(extra[:, :, :, :4][observed], x[observed])  # mask = 1: from the reference
    assert (extra[:, :, :, :4][~observed] == 0).all()  # mask = 0: no reference information
    with pytest.raises(ValueError, match="does not match"):
        reference_input(x, mask[:, :2])


def test_task_masks_follow_their_definitions():
    cfg = get_preset("tiny")
    frames = make_frames(cfg, 3)
    vc, lidar = cfg.sensors.num_cameras, cfg.sensors.lidar_view
    rng = np.random.default_rng(0)
    assert set(TASKS) == {"unconditional", "first_frame_all", "first_frame_single", "object_completion"}
    assert task_mask("unconditional", cfg, frames, rng, RCFG).sum() == 0
    for _ in range(5):
        m = task_mask("first_frame_single", cfg, frames, rng, RCFG)
        assert m.shape == (3, cfg.sensors.num_views, 1, *cfg.latent_hw)
        per_view = m[0].reshape(cfg.sensors.num_views, -1)
        assert m[1:].sum() == 0 and (per_view.all(1).sum(), per_view.any(1).sum()) == (1, 1)
        assert not per_view[lidar].any()  # a single *camera* view
    always = replace(RCFG, lidar_reference_prob=1.0)
    m = task_mask("first_frame_all", cfg, frames, rng, always)
    assert m[0].all() and m[1:].sum() == 0
    never = replace(RCFG, lidar_reference_prob=0.0)
    m = task_mask("first_frame_all", cfg, frames, rng, never)
    assert m[0, :vc].all() and not m[0, lidar].any()
    with pytest.raises(ValueError, match="unknown task"):
        task_mask("inpaint", cfg, frames, rng, RCFG)
    with pytest.raises(ValueError, match="sum to 1"):
        ReferenceConfig(p_unconditional=0.5)


def test_object_completion_masks_exactly_the_projected_box_in_every_frame():
    cfg = get_preset("tiny")
    frames = make_frames(cfg, 3)
    m = task_mask("object_completion", cfg, frames, np.random.default_rng(1), RCFG)
    hidden = m[:, :, 0] == 0
    assert hidden.any() and (m[:, :, 0] == 1).any()
    # Exactly one object's region per frame: find which one and compare the whole mask.
    ids = [o.track_id for o in frames[0].objects]
    matches = [
        tid
        for tid in ids
        if all(np.array_equal(hidden[f], object_region(fr, tid, cfg, RCFG)) for f, fr in enumerate(frames))
    ]
    assert len(matches) == 1


@pytest.mark.parametrize("margin", [0, 2])
def test_object_region_covers_exactly_the_projected_boxes_latent_cells(margin):
    """Cameras: the latent cells of the box's pixel extent (hand-checked in test_sim_cameras's
    test_box_extent_hand_worked) grown by the margin; the simulator's crops use the same extent."""
    cfg = get_preset("default")  # 64x112 views: boxes are small relative to the latent cells
    frame = _frame_with_hard_objects(cfg)
    sim = ProceduralSimulator()
    d = cfg.vae.downsample
    for obj in frame.objects:
        region = object_region(frame, obj.track_id, cfg, replace(RCFG, margin_px=margin))
        for v in range(cfg.sensors.num_cameras):
            px = np.zeros((cfg.sensors.height, cfg.sensors.width), bool)
            box = sim.object_boxes_2d(frame, v).get(obj.track_id)
            if box is not None:
                x0, y0, x1, y1 = box
                px[max(0, y0 - margin) : y1 + margin, max(0, x0 - margin) : x1 + margin] = True
            np.testing.assert_array_equal(region[v], _cells(px, d), err_msg=f"{obj.track_id} view {v}")
    with pytest.raises(KeyError, match="not in frame"):
        object_region(frame, "ghost", cfg, RCFG)


def test_object_region_contains_every_rendered_pixel_and_lidar_return_of_the_object():
    """With the default margin, the region holds the object's anti-aliased edges too."""
    cfg = get_preset("default")
    frame = _frame_with_hard_objects(cfg)
    sim = ProceduralSimulator()
    d = cfg.vae.downsample
    spec, s = cfg.sensors.lidar, cfg.sensors
    for obj in frame.objects:
        without = frame.with_objects(tuple(o for o in frame.objects if o.track_id != obj.track_id))
        alone, rest = sim.render(frame), sim.render(without)
        region = object_region(frame, obj.track_id, cfg, RCFG)
        for v in range(cfg.sensors.num_cameras):
            changed = (alone.cameras[v] != rest.cameras[v]).any(-1)
            assert not (_cells(changed, d) & ~region[v]).any(), f"{obj.track_id} leaks out in view {v}"
        hit = np.argwhere(alone.lidar != rest.lidar)  # (beam, column) returns the object changed
        px = np.zeros((s.height, s.width), bool)
        for r, c in hit:
            rows = slice(r * s.height // spec.beams, -(-(r + 1) * s.height // spec.beams))
            cols = slice(c * s.width // spec.azimuth, -(-(c + 1) * s.width // spec.azimuth))
            px[rows, cols] = True
        lidar_region = region[cfg.sensors.lidar_view]
        assert not (_cells(px, d) & ~lidar_region).any(), f"{obj.track_id} LiDAR returns outside the region"
        assert lidar_region.mean() < 0.5  # a box, not the whole range map


def test_expanded_teacher_starts_as_the_teacher_whatever_the_reference():
    cfg = get_preset("tiny")
    teacher = perturbed(MultiViewDiT(cfg))
    model = expand_teacher(teacher)
    assert model.cfg.dit.in_channels_extra == reference_channels(cfg) == cfg.vae.latent_channels + 1
    cond = tiny_conditions(cfg, 2)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(1, *cfg.latent_shape(2), generator=gen)
    extra = torch.randn(1, 2, cfg.sensors.num_views, reference_channels(cfg), *cfg.latent_hw, generator=gen)
    t = torch.tensor([0.3])
    with torch.no_grad():
        torch.testing.assert_close(model(torch.cat([x, extra], dim=3), t, cond), teacher(x, t, cond))
    with pytest.raises(ValueError, match="without extra input channels"):
        expand_teacher(model)
