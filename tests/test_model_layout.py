"""Pixel-aligned layout conditioning: the raster's geometry and the DiT's extra input channels."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.model_fixtures import make_frames, make_sensors, perturbed, tiny_conditions
from world_model import Box3D, EgoState, MapGeometry, SceneFrame, SceneObject, ScenePrompt
from world_model.model import MultiViewDiT, build_condition_arrays, get_preset, make_text_encoder
from world_model.model.config import ModelConfig, with_layout
from world_model.model.layout import LAYOUT_CHANNELS, NEARNESS_LEVELS, layout_raster, lidar_nearness
from world_model.model.vae import lidar_to_images
from world_model.sim.demo import straight_road
from world_model.sim.simulator import ProceduralSimulator

VEHICLE, NEARNESS = LAYOUT_CHANNELS.index("vehicle"), LAYOUT_CHANNELS.index("nearness")
ROAD = LAYOUT_CHANNELS.index("road")


def _bus_ahead(cfg: ModelConfig, road: MapGeometry | None = None) -> SceneFrame:
    """A bus (11.5 x 2.6 x 3.2 m) straight ahead of the ego, its rear face 6 m in front of the sensors."""
    size = (11.5, 2.6, 3.2)
    bus = SceneObject("bus0", "bus", Box3D(center=(6.0 + size[0] / 2, 0.0, size[2] / 2), size=size, yaw=0.0))
    return SceneFrame(
        time=0.0,
        frame_index=0,
        ego=EgoState(x=0.0, y=0.0, yaw=0.0),
        objects=(bus,),
        map=road if road is not None else MapGeometry(),
        prompt=ScenePrompt(),
        rig=cfg.sensors.rig(),
        lidar=cfg.sensors.lidar,
        bev=cfg.sensors.bev,
    )


def test_shapes_and_disabled_layout_has_no_channels():
    off = get_preset("tiny")
    on = with_layout(off, True)
    frames = make_frames(off, 3)
    _, _, bev = make_sensors(off, 3)
    enc = make_text_encoder(off.text)
    h, w = off.latent_hw
    v = off.sensors.num_views
    assert build_condition_arrays(frames, bev, off, enc).layout.shape == (3, v, 0, h, w)
    lay = build_condition_arrays(frames, bev, on, enc).layout
    assert lay.shape == (3, v, len(LAYOUT_CHANNELS), h, w) and lay.dtype == np.float32
    assert on.layout.channels == len(LAYOUT_CHANNELS) and off.layout.channels == 0
    assert lay.min() >= 0.0 and lay.max() <= 1.0
    assert lay[:, :, VEHICLE].sum() > 0  # the fixture's cars ahead are in some view


def test_known_box_lands_on_known_latent_cells_of_the_front_camera():
    # Default rig: 112x64 pixels, 70-degree FoV -> fx = 56 / tan(35 deg) = 79.98; cameras 0.3 m
    # below the LiDAR, which is 1.84 m above the road. The bus's rear face (6 m ahead) spans
    # u = 56 -+ 79.98 * 1.3 / 6 = [38.7, 73.3] and v = 32 + 79.98 * [-1.66, 1.54] / 6 = [9.9, 52.5].
    # Latent cells are 8x8 pixels: columns 5..8 and rows 2..5 lie inside, columns <= 3 or >= 10
    # and rows 0 and 7 outside.
    cfg = get_preset("default")
    frame = _bus_ahead(cfg)
    bev = np.zeros(cfg.sensors.bev.shape, np.uint8)
    lay = layout_raster(frame, bev, cfg.sensors.lidar, cfg.latent_hw, supersample=4)
    front = frame.rig.names.index("FRONT")
    veh = lay[front, VEHICLE]
    assert np.all(veh[2:6, 5:9] == 1.0)
    assert veh[:, :4].sum() == 0 and veh[:, 10:].sum() == 0 and veh[0].sum() == 0 and veh[7].sum() == 0
    assert 0.0 < veh[1, 5] < 1.0 and 0.0 < veh[3, 4] < 1.0  # partly covered border cells
    near = lay[front, NEARNESS, 2:6, 5:9]
    assert np.all((near > 1 - 7.0 / 100) & (near < 1 - 6.0 / 100))  # ranges 6..7 m of max_range 100
    others = [v for v, n in enumerate(frame.rig.names) if n not in ("FRONT", "FRONT_LEFT", "FRONT_RIGHT")]
    assert lay[others, VEHICLE].sum() == 0


def test_known_box_in_the_lidar_view():
    # LiDAR view columns: azimuth +180 deg at column 0, 0 deg at the middle (14 latent columns of
    # 25.7 deg). The rear face spans azimuth +-12.2 deg (atan(1.3 / 6)): half of columns 6 and 7.
    # Elevation +10 (row 0) .. -30 deg (row 7, 5 deg per row): the face spans +12.8 .. -17.0 deg,
    # rows 0..4 fully (row 4 ends at -15 deg) and row 5 partly.
    cfg = get_preset("default")
    frame = _bus_ahead(cfg)
    lay = layout_raster(frame, np.zeros(cfg.sensors.bev.shape, np.uint8), cfg.sensors.lidar, cfg.latent_hw, 4)
    veh = lay[cfg.sensors.lidar_view, VEHICLE]
    assert np.allclose(veh[0:5, 6:8], 0.5, atol=0.15)
    assert veh[:, :6].sum() == 0 and veh[:, 8:].sum() == 0 and veh[6:].sum() == 0
    assert 0.0 < veh[5, 6] < 0.5


def test_lidar_view_nearness_is_the_simulated_range_map():
    # The raster's expected ranges equal the procedural LiDAR's, resampled to the view the same way.
    cfg = get_preset("default")
    frame = _bus_ahead(cfg, road=straight_road())
    sim = ProceduralSimulator()
    bev = sim.render_bev(frame)
    ranges = sim.render_lidar(frame)
    image = lidar_to_images(ranges, cfg)[0].numpy()  # [-1, 1] = [0, max_range], no return = +1
    sim_range = (image + 1.0) * 0.5 * cfg.sensors.lidar.max_range
    full = layout_raster(frame, bev, cfg.sensors.lidar, (cfg.sensors.height, cfg.sensors.width), 1)
    lay_range = (1.0 - full[cfg.sensors.lidar_view, NEARNESS]) * cfg.sensors.lidar.max_range
    seen = full[cfg.sensors.lidar_view, NEARNESS] > 0
    assert seen.mean() > 0.4
    assert np.median(np.abs(lay_range[seen] - sim_range[seen])) < 0.5
    on_bus = full[cfg.sensors.lidar_view, VEHICLE] == 1.0
    assert on_bus.sum() > 20 and np.median(np.abs(lay_range[on_bus] - sim_range[on_bus])) < 0.5
    # the decoder's nearness map is that channel in bytes, one ray per view pixel
    near = lidar_nearness(frame, cfg.sensors.lidar, (cfg.sensors.height, cfg.sensors.width))
    assert near.dtype == np.uint8 and near.shape == (cfg.sensors.height, cfg.sensors.width)
    assert np.abs(near / NEARNESS_LEVELS - full[cfg.sensors.lidar_view, NEARNESS]).max() <= 0.5 / NEARNESS_LEVELS + 1e-6
    # the bus's face 6 m ahead, in the middle columns, at the horizon's rows
    mid = cfg.sensors.width // 2
    assert abs((1 - near[20:28, mid] / NEARNESS_LEVELS).mean() * cfg.sensors.lidar.max_range - 6.0) < 0.5


def test_road_and_objects_agree_with_the_simulators_pixels():
    cfg = get_preset("default")
    frame = _bus_ahead(cfg, road=straight_road())
    sim = ProceduralSimulator()
    full = layout_raster(frame, sim.render_bev(frame), cfg.sensors.lidar, (cfg.sensors.height, cfg.sensors.width), 1)
    cams, _ = sim.object_masks(frame)
    boxes = full[: cfg.sensors.num_cameras, VEHICLE] > 0.5
    iou = (boxes & cams).sum() / (boxes | cams).sum()
    assert iou > 0.7  # meshes are not boxes, but they fill most of them
    front = frame.rig.names.index("FRONT")
    # The bottom pixel row sees the ground 1.54 / ((63.5 - 32) / 79.98) = 3.91 m ahead; the road's
    # left edge (y = +2 m) falls at u = 56 - 79.98 * 2 / 3.91 = 15.1 and the road goes on rightwards.
    bottom = full[front, ROAD, -1]
    assert bottom[:14].sum() == 0 and np.all(bottom[17:] == 1.0)
    back = frame.rig.names.index("BACK")
    assert full[back, :, : cfg.sensors.height // 2].sum() == 0  # above the horizon: nothing but sky


def test_object_occludes_road_and_farther_object():
    cfg = get_preset("default")
    frame = _bus_ahead(cfg, road=straight_road())
    hidden = SceneObject("car1", "car", Box3D(center=(30.0, 0.0, 0.8), size=(4.5, 1.9, 1.6), yaw=0.0))
    behind = frame.with_objects((*frame.objects, hidden))
    bev = ProceduralSimulator().render_bev(frame)
    a = layout_raster(frame, bev, cfg.sensors.lidar, cfg.latent_hw, 4)
    b = layout_raster(behind, bev, cfg.sensors.lidar, cfg.latent_hw, 4)
    assert np.array_equal(a, b)  # the car behind the bus is not seen
    front = frame.rig.names.index("FRONT")
    cell = a[front, :, 4, 6]
    assert cell[VEHICLE] == 1.0 and cell[ROAD] == 0.0


def _first_object_hits_by_brute_force(frame: SceneFrame, origins: np.ndarray, dirs: np.ndarray):
    """Every ray against every box (slab test, no culling): the nearest entry and its object index."""
    o = np.repeat(origins, dirs.shape[1], axis=0)
    d = dirs.reshape(-1, 3)
    best_t, best = np.full(len(d), np.inf), np.full(len(d), -1)
    for i, box in enumerate(frame.object_boxes_lidar()):
        c, s = np.cos(box.yaw), np.sin(box.yaw)
        to_box = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        ob, db = (o - np.asarray(box.center)) @ to_box.T, d @ to_box.T
        half = 0.5 * np.asarray(box.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - ob) / db, (half - ob) / db
        t_in = np.nanmax(np.minimum(t1, t2), axis=1)
        t_out = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_out >= t_in) & (t_in > 0.05) & (t_in < best_t)
        best_t[hit], best[hit] = t_in[hit], i
    return best_t, best


def test_first_hits_equal_testing_every_ray_against_every_box():
    from world_model.model.layout import _GROUP_OF, _first_hits, view_rays

    cfg = get_preset("default")
    rng = np.random.default_rng(5)
    categories = ["car", "bus", "pedestrian", "cone", "truck", "cyclist"]
    objects = []
    for i in range(40):  # around the ego, beside the cameras, behind them, overlapping each other
        size = (rng.uniform(0.4, 12.0), rng.uniform(0.4, 3.0), rng.uniform(0.5, 3.5))
        center = (rng.uniform(-40, 60), rng.uniform(-25, 25), size[2] / 2 + rng.uniform(-0.2, 0.5))
        box = Box3D(center=center, size=size, yaw=float(rng.uniform(-np.pi, np.pi)))
        objects.append(SceneObject(f"o{i}", categories[i % len(categories)], box))
    frame = _bus_ahead(cfg).with_objects(tuple(objects))
    origins, dirs = view_rays(frame.rig, cfg.sensors.lidar, 24, 40)
    _, t_obj, group = _first_hits(frame, origins, dirs)
    want_t, want = _first_object_hits_by_brute_force(frame, origins, dirs)
    assert (want >= 0).mean() > 0.1  # many rays hit something
    np.testing.assert_allclose(t_obj, want_t, rtol=1e-9)
    channels = np.array([LAYOUT_CHANNELS.index(_GROUP_OF[o.category]) for o in objects])
    assert np.array_equal(group, np.where(want >= 0, channels[want], -1))


def test_bad_layout_settings_raise():
    cfg = get_preset("default")
    frame = _bus_ahead(cfg)
    with pytest.raises(ValueError, match="supersample"):
        layout_raster(frame, np.zeros(cfg.sensors.bev.shape, np.uint8), cfg.sensors.lidar, cfg.latent_hw, 0)
    with pytest.raises(ValueError, match="bev must have the frame's BEV shape"):
        layout_raster(frame, np.zeros((3, 3, 3), np.uint8), cfg.sensors.lidar, cfg.latent_hw, 2)
    with pytest.raises(ValueError, match="layout.supersample"):
        replace(cfg, layout=replace(cfg.layout, supersample=0))


def test_config_round_trip():
    cfg = with_layout(get_preset("tiny"), True)
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg


def test_tiny_teacher_forward_backward_with_layout():
    cfg = with_layout(get_preset("tiny"), True)
    torch.manual_seed(0)
    model = perturbed(MultiViewDiT(cfg))
    cond = tiny_conditions(cfg, 2, batch=2)
    assert cond.layout.shape == (2, 2, cfg.sensors.num_views, len(LAYOUT_CHANNELS), *cfg.latent_hw)
    x = torch.randn(2, *cfg.latent_shape(2))
    t = torch.full((2,), 0.5)
    model.train()
    v = model(x, t, cond)
    assert v.shape == x.shape
    v.square().mean().backward()
    c, p = cfg.vae.latent_channels, cfg.dit.patch
    layout_cols = model.patch_in.weight.grad[:, c * p * p : (c + cfg.layout.channels) * p * p]
    assert layout_cols.abs().sum() > 0  # the layout reaches the loss
    model.eval()
    with torch.no_grad():
        moved = replace(cond, layout=cond.layout.roll(1, dims=-1))
        assert not torch.allclose(model(x, t, cond), model(x, t, moved))
        # Dropped controls (the unconditional branch of guidance) drop the layout too.
        assert torch.allclose(model(x, t, cond.with_drop(True)), model(x, t, moved.with_drop(True)))


def test_reference_model_keeps_the_teachers_layout_columns_and_samples_a_first_frame():
    from world_model.model import SensorVAE
    from world_model.model.reference import ReferenceGenerator, expand_teacher, reference_channels

    cfg = with_layout(get_preset("tiny"), True)
    torch.manual_seed(0)
    teacher = perturbed(MultiViewDiT(cfg))
    reference = expand_teacher(teacher).eval()
    cond = tiny_conditions(cfg, 1, batch=2)
    x = torch.randn(2, *cfg.latent_shape(1))
    extra = torch.randn(2, 1, cfg.sensors.num_views, reference_channels(cfg), *cfg.latent_hw)
    t = torch.full((2,), 0.3)
    with torch.no_grad():  # the new reference channels start at zero: the teacher's velocity, layout included
        assert torch.allclose(teacher(x, t, cond), reference(torch.cat([x, extra], dim=3), t, cond), atol=1e-5)
    gen = ReferenceGenerator(perturbed(reference, seed=1), perturbed(SensorVAE(cfg), scale=0.05))
    lat, obs = gen.first_frame(cond, steps=2, seed=3)
    moved, _ = gen.first_frame(replace(cond, layout=cond.layout.roll(1, dims=-1)), steps=2, seed=3)
    assert lat.shape == (2, 1, *cfg.latent_shape(1)[1:]) and not torch.equal(lat, moved)


def test_layout_training_flag_switches_the_stage_config():
    import argparse

    from world_model.train.student_flags import add_student_flags, stage_config

    p = argparse.ArgumentParser()
    add_student_flags(p)
    preset = get_preset("tiny")
    assert stage_config(p.parse_args(["--layout"]), preset).layout.channels == len(LAYOUT_CHANNELS)
    assert stage_config(p.parse_args(["--no-layout"]), preset).layout.channels == 0
    assert stage_config(p.parse_args([]), preset).layout == preset.layout


def test_one_decoder_switch_turns_every_label_map_channel_on_and_the_config_refuses_the_old_flags():
    from world_model.bundle import load_bundle_files
    from world_model.model.config import DECODER_LABEL_CHANNELS, without_label_decoder
    from world_model.raster.classes import LABEL_CLASSES

    on = with_layout(get_preset("tiny"), True)
    assert on.layout.decoder and on.layout.label_channels == len(LABEL_CLASSES) + 5
    assert DECODER_LABEL_CHANNELS[-1] == "lidar_nearness" and without_label_decoder(on).layout.label_channels == 0
    shipped = ModelConfig.from_dict(load_bundle_files().model_config)
    assert shipped.layout.decoder and shipped.layout.label_channels == len(DECODER_LABEL_CHANNELS)
    for flag in ("decoder_style", "decoder_paint", "decoder_surface", "decoder_lidar"):
        old = on.to_dict()
        old["layout"][flag] = True
        with pytest.raises(ValueError, match=flag):
            ModelConfig.from_dict(old)
    missing = on.to_dict()
    del missing["layout"]
    with pytest.raises(KeyError, match="layout"):
        ModelConfig.from_dict(missing)
