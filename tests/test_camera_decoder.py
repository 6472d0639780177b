"""The cameras' own decoder: it draws the cameras alone, and the LiDAR, the latents' cache key and
the range head's stay those of the VAE it was copied from."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from tests.model_fixtures import make_sensors
from world_model.bundle import CheckpointError, export_bundle, load_bundle_files
from world_model.model.config import get_preset, with_layout
from world_model.model.range_head import finished_digest
from world_model.model.vae import SensorVAE
from world_model.raster.classes import CLASS_PLANE, LABEL_CLASSES, ROAD, VEHICLE
from world_model.train.camera_decoder_stage import with_camera_decoder
from world_model.train.data import encoder_digest
from world_model.train.range_head_stage import with_range_head
from world_model.train.vae_stage import CameraTuning


def _pair() -> tuple[SensorVAE, SensorVAE]:
    """A label-drawing VAE with a range head, and the same VAE with a camera decoder copied from
    its decoder and then moved away from it."""
    cfg = with_range_head(with_layout(get_preset("tiny"), True))
    torch.manual_seed(0)
    shared = SensorVAE(cfg).eval()
    for mod in shared.decoder.label_mods:
        torch.nn.init.normal_(mod.conv.weight, std=0.5)
    own = SensorVAE(with_camera_decoder(cfg)).eval()
    missing, unexpected = own.load_state_dict(shared.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("camera_decoder.") for k in missing)
    own.camera_decoder.load_state_dict(shared.decoder.state_dict(), strict=False)
    with torch.no_grad():
        own.camera_decoder.conv_out.bias.add_(0.5)
    return shared, own


def _maps(cfg, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    h, w, v = cfg.sensors.height, cfg.sensors.width, cfg.sensors.num_cameras
    classes = rng.integers(len(LABEL_CLASSES), size=(t, v, h, w))
    labels = np.stack([classes, rng.integers(256, size=(t, v, h, w)), rng.integers(256, size=(t, v, h, w))], 2)
    style = rng.standard_normal(cfg.text.dim).astype(np.float32)
    near = rng.integers(256, size=(t, h, w)).astype(np.uint8)
    lidar = cfg.sensors.lidar
    range_near = rng.integers(256, size=(t, lidar.beams, lidar.azimuth)).astype(np.uint8)
    return labels.astype(np.uint8), style, near, range_near


def test_the_camera_decoder_draws_the_cameras_and_leaves_the_lidar_as_the_shared_decoder_draws_it():
    shared, own = _pair()
    cams, lidar, _ = make_sensors(own.cfg, 2)
    latents = own.encode_frames(cams, lidar.astype(np.float32))
    labels, style, near, range_near = _maps(own.cfg, 2)
    kwargs = {"labels": labels, "style": style, "nearness": near, "range_nearness": range_near}
    shared_cams, shared_lidar = shared.decode_frames(latents, **kwargs)
    own_cams, own_lidar = own.decode_frames(latents, **kwargs)
    assert np.array_equal(own_lidar, shared_lidar) and not np.array_equal(own_cams, shared_cams)
    # a batch of both views: each latent drawn by its view's decoder, as when decoded apart
    z = torch.cat([latents[:, 0], latents[:, -1]])
    ids = torch.from_numpy(np.concatenate([labels[:, 0], np.zeros_like(labels[:, 0])]))
    styles = torch.from_numpy(style).expand(len(z), -1)
    nearness = torch.cat([torch.zeros(2, *near.shape[1:], dtype=torch.uint8), torch.from_numpy(near)])
    lidar_rows = torch.tensor([False, False, True, True])
    mixed = own.decode(z, ids, styles, nearness, lidar_rows)
    assert torch.allclose(mixed[:2], own.decode(z[:2], ids[:2], styles[:2], nearness[:2]), atol=1e-6)
    assert torch.allclose(mixed[2:], shared.decode(z[2:], ids[2:], styles[2:], nearness[2:]), atol=1e-6)
    with pytest.raises(ValueError, match="layout.decoder"):
        SensorVAE(with_camera_decoder(get_preset("tiny")))


def test_the_camera_decoder_leaves_the_latent_cache_key_and_the_range_heads_digest_alone():
    shared, own = _pair()
    assert encoder_digest(own) == encoder_digest(shared)
    assert finished_digest(own.state_dict()) == finished_digest(shared.state_dict())
    with torch.no_grad():
        own.decoder.conv_out.bias.add_(0.5)  # the LiDAR's decoder: another head's
    assert finished_digest(own.state_dict()) != finished_digest(shared.state_dict())


def _run_with_decoders(root, camera: dict[str, torch.Tensor], source: dict[str, torch.Tensor]):
    config = {"name": "tiny", "layout": {"decoder": True, "range_head": True}}
    for stage, state, meta in (
        ("vae", {"w": torch.ones(3)}, {}),
        ("dmd", {"w": torch.arange(4.0)}, {}),
        ("range_head", source, {"finishes": finished_digest(source)}),
        ("camera_decoder", camera, {}),
    ):
        (root / stage).mkdir(parents=True)
        save_file(state, str(root / stage / "model.safetensors"))
        layout = {**config["layout"], "camera_decoder": stage == "camera_decoder"}
        (root / stage / "model.json").write_text(json.dumps({"model_config": {**config, "layout": layout}, **meta}))
    return root


def test_a_bundle_takes_the_camera_decoder_only_with_the_vae_it_was_trained_on(tmp_path):
    source = {"decoder.w": torch.ones(2), "range_head.w": torch.zeros(2)}
    camera = {**source, "camera_decoder.w": torch.full((2,), 3.0)}
    run = _run_with_decoders(tmp_path / "run", camera, source)
    files = load_bundle_files(export_bundle(run, tmp_path / "bundle"))
    assert files.manifest["components"]["vae"]["stage"] == "camera_decoder"
    assert files.model_config["layout"] == {"decoder": True, "range_head": True, "camera_decoder": True}
    # the range head trained again after the camera decoder: the camera decoder's copy is stale
    save_file({**source, "range_head.w": torch.ones(2)}, str(run / "range_head" / "model.safetensors"))
    with pytest.raises(CheckpointError, match="train --stage camera_decoder again"):
        export_bundle(run, tmp_path / "stale")


def test_the_env_draws_the_cameras_with_the_bundles_camera_decoder_and_the_lidar_as_before(range_head_bundle, tmp_path):
    import copy

    from m4world_env.env import M4WorldEnv
    from world_model.bundle import save_bundle
    from world_model.model.config import ModelConfig

    files = load_bundle_files(range_head_bundle)
    cfg = with_camera_decoder(ModelConfig.from_dict(files.model_config))
    vae = SensorVAE(cfg)
    vae.load_state_dict(files.tensors["vae"], strict=False)
    vae.camera_decoder.load_state_dict(vae.decoder.state_dict(), strict=False)
    with torch.no_grad():
        vae.camera_decoder.conv_out.bias.add_(0.5)
    tensors = {**copy.copy(files.tensors), "vae": vae.state_dict()}
    configs = {"reference": files.component_config("reference")}
    bundle = save_bundle(tmp_path / "camera_decoder", cfg.to_dict(), tensors, component_configs=configs)

    def episode(path) -> list[dict[str, np.ndarray]]:
        env = M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(path))
        obs = [env.reset(seed=0)[0]]
        for _ in range(2):
            obs.append(env.step(np.zeros(env.action_space.shape, np.float32))[0])
        return obs

    own, shared = episode(bundle), episode(range_head_bundle)
    for a, b in zip(own, shared, strict=True):
        assert np.array_equal(a["lidar"], b["lidar"]) and not np.array_equal(a["cameras"], b["cameras"])


def test_the_camera_tuning_learns_the_recording_about_the_vehicles_and_the_shared_drawing_elsewhere():
    labels = torch.full((1, 3, 10, 5), ROAD, dtype=torch.uint8)
    labels[0, CLASS_PLANE, 2:5, 1] = VEHICLE  # rows 2-4: its edge is row 5, the band rows 3-7
    images, shared, weights = torch.ones(1, 3, 10, 5), torch.zeros(1, 3, 10, 5), torch.full((1, 1, 10, 5), 2.0)
    targets, weighted = CameraTuning(edge_weight=10.0, edge_rows=2, margin=0).targets(images, shared, weights, labels)
    zone = torch.zeros(10, 5, dtype=torch.bool)
    zone[2:8, 1] = True  # the vehicle and the band under it
    assert torch.equal(targets[0], zone.float().expand(3, -1, -1))
    assert weighted[0, 0, :, 1].tolist() == [2.0, 2.0, 2.0, 20.0, 20.0, 20.0, 20.0, 20.0, 2.0, 2.0]
    assert torch.equal(weighted[0, 0, :, [0, 2, 3, 4]], weights[0, 0, :, [0, 2, 3, 4]])  # no vehicle there
    grown, _ = CameraTuning(margin=1).targets(images, shared, weights, labels)
    assert grown[0, 0, 1:9, 0:3].all() and not grown[0, 0, :, 3:].any() and not grown[0, 0, [0, 9]].any()
    # no vehicle in view: the shared drawing everywhere, no weight changed
    road = torch.full_like(labels, ROAD)
    targets, weighted = CameraTuning().targets(images, shared, weights, road)
    assert torch.equal(targets, shared) and torch.equal(weighted, weights)
