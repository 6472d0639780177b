"""VAE: shapes, camera/LiDAR normalization round trips, no-return handling, sampling to Observations."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.model_fixtures import make_sensors, perturbed, tiny_conditions
from world_model import Observation
from world_model.model import MultiViewDiT, SensorVAE, generate, get_preset
from world_model.model.config import with_layout
from world_model.model.vae import (
    LABEL_DECODER_WEIGHTS,
    LabelModulation,
    cameras_to_images,
    images_to_cameras,
    images_to_lidar,
    lidar_to_images,
    weighted_l1,
)
from world_model.raster.classes import CLASS_PLANE, LABEL_CLASSES, NO_LABEL, PAINT_PLANE, SURFACE_PLANE


def test_lidar_normalization_round_trip_and_no_return():
    cfg = get_preset("default")
    spec = cfg.sensors.lidar
    rng = np.random.default_rng(0)
    # Smooth ranges (a resize round trip cannot keep per-column noise), with a no-return band on top.
    az = np.linspace(0, 2 * np.pi, spec.azimuth)
    ranges = np.broadcast_to(30 + 20 * np.sin(az)[None], (spec.beams, spec.azimuth)).astype(np.float32).copy()
    ranges[:4] = spec.no_return
    img = lidar_to_images(ranges, cfg)
    assert img.shape == (3, cfg.sensors.height, cfg.sensors.width)
    assert img.min() >= -1 and img.max() <= 1
    assert torch.allclose(img[:, :4], torch.ones_like(img[:, :4]))  # no return -> far (+1), not 0 m
    back = images_to_lidar(img, spec, cfg.vae.lidar_no_return_fraction)
    assert back.shape == (spec.beams, spec.azimuth) and back.dtype == np.float32
    assert (back[:3] == spec.no_return).all()  # the boundary row blends on resampling
    assert np.abs(back[5:] - ranges[5:]).mean() < 0.5
    # Exact linear map: 0 m -> -1, 50 m -> 0, 100 m -> +1 (before resizing).
    flat = torch.as_tensor(rng.uniform(1, 95, size=(4, 7)).astype(np.float32))
    tiny = replace(cfg, sensors=replace(cfg.sensors, height=8, width=8), vae=replace(cfg.vae, channel_mults=(1,)))
    tiny_spec = replace(spec, beams=8, azimuth=8)
    full = torch.nn.functional.interpolate(flat[None, None], size=(8, 8), mode="nearest")[0, 0].numpy()
    norm = lidar_to_images(full, tiny)[0]
    assert torch.allclose(norm, torch.as_tensor(full / 50.0 - 1.0), atol=1e-5)
    assert np.allclose(images_to_lidar(norm[None].expand(3, -1, -1), tiny_spec, 0.97), full, atol=1e-3)


def test_camera_round_trip_exact():
    cams = np.random.default_rng(0).integers(0, 256, size=(2, 5, 6, 3), dtype=np.uint8)
    img = cameras_to_images(cams)
    assert img.shape == (2, 3, 5, 6) and img.min() >= -1 and img.max() <= 1
    assert np.array_equal(images_to_cameras(img), cams)


def test_vae_shapes_and_latent_normalization():
    cfg = get_preset("tiny")
    torch.manual_seed(0)
    vae = SensorVAE(cfg).eval()
    cams, lidar, _ = make_sensors(cfg, 3)
    lat = vae.encode_frames(cams, lidar.astype(np.float32))
    assert lat.shape == cfg.latent_shape(3)
    images = cameras_to_images(cams.reshape(-1, *cams.shape[2:]))
    vae.set_latent_stats(images)
    z = vae.encode(images)
    assert torch.allclose(z.mean(dim=(0, 2, 3)), torch.zeros(cfg.vae.latent_channels), atol=1e-4)
    assert torch.allclose(z.transpose(0, 1).flatten(1).std(dim=1), torch.ones(cfg.vae.latent_channels), atol=1e-3)
    out_cams, out_lidar = vae.decode_frames(lat)
    assert out_cams.shape == cams.shape and out_cams.dtype == np.uint8
    assert out_lidar.shape == lidar.shape and out_lidar.dtype == np.float32
    # decode runs the decoder on a channels-last copy (faster on CPU): the values of the plain layout
    z = lat.flatten(0, 1)
    plain = vae.decoder(z * vae.latent_std[:, None, None] + vae.latent_mean[:, None, None])
    assert torch.allclose(vae.decode(z), plain, atol=1e-5)


def test_bf16_switch_decodes_cameras_in_bf16_and_lidar_in_fp32():
    cfg = get_preset("tiny")
    torch.manual_seed(0)
    fp32 = SensorVAE(cfg).eval()
    bf16 = SensorVAE(replace(cfg, dit=replace(cfg.dit, autocast_bf16=True))).eval()
    bf16.load_state_dict(fp32.state_dict())
    lat = torch.randn(3, *cfg.latent_shape(1)[1:]) * 3
    (c32, l32), (c16, l16) = fp32.decode_frames(lat), bf16.decode_frames(lat)
    assert np.array_equal(l32, l16)  # ranges keep fp32 precision
    diff = np.abs(c32.astype(int) - c16)
    assert diff.max() <= 3 and diff.mean() < 0.5 and diff.max() > 0  # bf16 did run, and barely shows


def test_generate_returns_observations():
    cfg = get_preset("tiny")
    torch.manual_seed(0)
    model, vae = perturbed(MultiViewDiT(cfg)), SensorVAE(cfg).eval()
    cond = tiny_conditions(cfg, 2, batch=2)
    obs = generate(model, vae, cond, torch.Generator().manual_seed(0))
    again = generate(model, vae, cond, torch.Generator().manual_seed(0))
    assert len(obs) == 2 and len(obs[0]) == 2 and isinstance(obs[0][0], Observation)
    assert obs[0][0].cameras.shape == (cfg.sensors.num_cameras, cfg.sensors.height, cfg.sensors.width, 3)
    assert obs[0][0].lidar.shape == (cfg.sensors.lidar.beams, cfg.sensors.lidar.azimuth)
    assert np.array_equal(obs[1][1].cameras, again[1][1].cameras)  # deterministic given the generator


def test_weighted_l1_is_plain_l1_under_unit_weights_and_follows_the_weights():
    gen = torch.Generator().manual_seed(0)
    rec, target = torch.randn(3, 3, 8, 10, generator=gen), torch.randn(3, 3, 8, 10, generator=gen)
    ones = torch.ones(3, 1, 8, 10)
    plain = torch.nn.functional.l1_loss(rec, target, reduction="none").mean(dim=(1, 2, 3))
    torch.testing.assert_close(weighted_l1(rec, target, ones), plain)
    # All the weight on one pixel: the loss is that pixel's mean error over channels.
    w = torch.zeros(3, 1, 8, 10)
    w[:, :, 2, 5] = 4.0
    torch.testing.assert_close(weighted_l1(rec, target, w), (rec - target).abs()[:, :, 2, 5].mean(dim=1))
    # Up-weighting a region moves the loss towards that region's error.
    box = ones.clone()
    box[:, :, :4] = 10.0
    top, bottom = (rec - target).abs()[:, :, :4].mean(dim=(1, 2, 3)), (rec - target).abs()[:, :, 4:].mean(dim=(1, 2, 3))
    torch.testing.assert_close(weighted_l1(rec, target, box), (10 * top + bottom) / 11)


def test_label_decoder_starts_as_the_plain_one_and_then_draws_the_label_maps_in_the_scene_style():
    plain_cfg = get_preset("tiny")
    cfg = with_layout(plain_cfg, True)
    torch.manual_seed(0)
    plain = SensorVAE(plain_cfg).eval()
    vae = SensorVAE(cfg).eval()
    missing, unexpected = vae.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith(LABEL_DECODER_WEIGHTS) for k in missing)
    cams, lidar, _ = make_sensors(cfg, 2)
    lat = vae.encode_frames(cams, lidar.astype(np.float32))
    h, w = cfg.sensors.height, cfg.sensors.width
    rng = np.random.default_rng(0)
    labels = np.stack(
        [
            rng.integers(len(LABEL_CLASSES), size=(2, cfg.sensors.num_cameras, h, w)),
            rng.integers(256, size=(2, cfg.sensors.num_cameras, h, w)),
            rng.integers(256, size=(2, cfg.sensors.num_cameras, h, w)),
        ],
        axis=2,
    ).astype(np.uint8)
    style, other_style = (v / np.linalg.norm(v) for v in rng.standard_normal((2, cfg.text.dim)).astype(np.float32))
    near = rng.integers(256, size=(2, h, w)).astype(np.uint8)
    # zero-initialized modulations: the fine-tuning starts from the plain decoder's images
    assert vae.draws_labels and vae.decoder.style_dim == cfg.text.dim and vae.decoder.nearness_gate is not None
    drawn_frames = vae.decode_frames(lat, labels=labels, style=style, nearness=near)
    for a, b in zip(drawn_frames, plain.decode_frames(lat), strict=True):
        assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="label map"):
        vae.decode_frames(lat, style=style, nearness=near)
    with pytest.raises(ValueError, match="label map"):
        vae.decode_frames(lat, labels=labels[:, :2], style=style, nearness=near)
    with pytest.raises(ValueError, match="class ids, paint and surface"):
        vae.decode_frames(lat, labels=labels[:, :, :SURFACE_PLANE], style=style, nearness=near)  # no surface
    with pytest.raises(ValueError, match="style"):
        vae.decode_frames(lat, labels=labels, nearness=near)
    with pytest.raises(ValueError, match="nearness"):
        vae.decode_frames(lat, labels=labels, style=style)
    with pytest.raises(ValueError, match="nearness"):
        vae.decode_frames(lat, labels=labels, style=style, nearness=near[:, :, :-1])

    for mod in vae.decoder.label_mods:
        torch.nn.init.normal_(mod.conv.weight, std=0.5)
        torch.nn.init.normal_(mod.style.weight, std=0.5)
    z = lat[:, 0]
    ids = torch.from_numpy(labels[:, 0])
    styles = torch.from_numpy(style).expand(len(z), -1)
    drawn = vae.decode(z, ids, styles)
    other_classes = ids.clone()
    other_classes[:, CLASS_PLANE] = torch.from_numpy(labels[:, 1, CLASS_PLANE])
    assert not torch.allclose(drawn, vae.decode(z, other_classes, styles))  # follows the classes
    repainted = ids.clone()
    repainted[:, PAINT_PLANE] = 255 - repainted[:, PAINT_PLANE]
    assert not torch.allclose(drawn, vae.decode(z, repainted, styles))  # and the paint
    resurfaced = ids.clone()
    resurfaced[:, SURFACE_PLANE] = 255 - resurfaced[:, SURFACE_PLANE]
    assert not torch.allclose(drawn, vae.decode(z, resurfaced, styles))  # and the surface
    assert not torch.allclose(drawn, vae.decode(z, ids, torch.from_numpy(other_style).expand(len(z), -1)))  # the style
    # NO_LABEL without paint is the all-zero input, the same as giving no labels (the LiDAR view): no style either
    none = torch.zeros_like(ids)
    none[:, CLASS_PLANE] = NO_LABEL
    assert torch.equal(vae.decode(z, none, styles), vae.decode(z))
    # the LiDAR view has no label map: its ranges depend on neither the cameras' labels nor the style,
    # but follow its nearness map, which the cameras do not read
    cams, lidar_ranges = vae.decode_frames(lat, labels=labels, style=style, nearness=near)
    assert np.array_equal(lidar_ranges, vae.decode_frames(lat, labels=labels * 0, style=other_style, nearness=near)[1])
    other_cams, other_ranges = vae.decode_frames(lat, labels=labels, style=style, nearness=255 - near)
    assert not np.array_equal(lidar_ranges, other_ranges) and np.array_equal(cams, other_cams)


def test_the_nearness_gate_learns_to_move_the_lidar_to_the_scenes_ranges_and_leaves_the_cameras():
    cfg = with_layout(get_preset("tiny"), True)
    torch.manual_seed(0)
    vae = SensorVAE(cfg)
    h, w = cfg.sensors.height, cfg.sensors.width
    z = torch.randn(2, cfg.vae.latent_channels, *cfg.latent_hw)
    near = torch.randint(1, 256, (2, h, w), dtype=torch.uint8)
    near[:, : h // 4] = 0  # nothing in range: the decoder's own output stays
    labels = torch.zeros(2, 3, h, w, dtype=torch.uint8)
    style = torch.randn(2, cfg.text.dim)
    lidar_before, cams_before = vae.decode(z, None, None, near), vae.decode(z, labels, style)
    scene = 1.0 - 2.0 * near.float()[:, None].expand(-1, 3, -1, -1) / 255
    (vae.decode(z, None, None, near) - scene).abs().mean().backward()  # zero-initialized, yet it learns
    assert vae.decoder.nearness_gate.bias.grad.item() < 0  # descending raises the share
    with torch.no_grad():
        vae.decoder.nearness_gate.bias.fill_(10.0)  # the whole share
        lidar = vae.decode(z, None, None, near)
        far = (near == 0)[:, None].expand_as(lidar)
        assert torch.allclose(lidar[~far], scene[~far], atol=1e-5) and torch.equal(lidar[far], lidar_before[far])
        assert torch.equal(vae.decode(z, labels, style), cams_before)  # a camera reads no nearness


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_label_modulation_pools_each_cell_as_the_area_mean(dtype):
    """The label maps reach each level as the mean over its cells, bit for bit adaptive pooling's."""
    torch.manual_seed(0)
    mod = LabelModulation(label_channels=5, channels=4).to(dtype)
    torch.nn.init.normal_(mod.conv.weight)
    labels = torch.rand(3, 5, 16, 28).to(dtype)
    for h, w in ((2, 4), (4, 7), (8, 14), (16, 28)):
        x = torch.randn(3, 4, h, w).to(dtype)
        pooled = torch.nn.functional.adaptive_avg_pool2d(labels, (h, w))
        gamma, beta = mod.conv(pooled).chunk(2, dim=1)
        torch.testing.assert_close(mod(x, labels), x * (1.0 + gamma) + beta, rtol=0, atol=0)
