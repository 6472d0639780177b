"""The range head: the LiDAR finished at the range map's resolution, and its loss."""

import numpy as np
import pytest
import torch

from world_model.model.layout import RANGE_LEVELS
from world_model.model.range_head import RangeHead, range_loss
from world_model.model.vae import images_to_lidar, ranges_to_image_values
from world_model.sensors import LidarSpec

SPEC = LidarSpec(beams=8, azimuth=64, max_range=100.0)


def test_an_untrained_head_is_the_view_stretched_as_without_it():
    torch.manual_seed(0)
    view = torch.rand(2, 3, 16, 28) * 2 - 1
    nearness = torch.randint(0, RANGE_LEVELS + 1, (2, SPEC.beams, SPEC.azimuth), dtype=torch.int32).to(torch.uint16)
    out = RangeHead()(view.mean(dim=1, keepdim=True), nearness)
    assert out.shape == (2, 1, SPEC.beams, SPEC.azimuth)
    without = images_to_lidar(view, SPEC, 0.99)
    np.testing.assert_allclose(ranges_to_metres(out[:, 0]), without, atol=1e-4)


def ranges_to_metres(values: torch.Tensor) -> np.ndarray:
    from world_model.model.vae import image_values_to_ranges

    return image_values_to_ranges(values, SPEC, 0.99)


def test_a_full_share_stands_the_scene_at_the_range_maps_resolution_with_its_edges():
    """A car one column wide of the view: the head at share 1 puts its range on its own columns
    only, to the centimetre (a byte's 0.39 m steps would not tell 25.0 m from 25.2 m), and no return
    where nothing is in range."""
    head = RangeHead()
    with torch.no_grad():
        head.net[-1].bias.fill_(1.0)  # share 1 everywhere
    view = torch.zeros(1, 1, 16, 28)  # 50 m everywhere
    nearness = torch.zeros(1, SPEC.beams, SPEC.azimuth, dtype=torch.uint16)
    nearness[0, 3:5, 30:33] = round(RANGE_LEVELS * (1 - 25.2 / SPEC.max_range))  # a car at 25.2 m
    nearness[0, 6:] = round(RANGE_LEVELS * (1 - 8.0 / SPEC.max_range))  # the road at 8 m
    metres = ranges_to_metres(head(view, nearness)[:, 0])[0]
    assert np.allclose(metres[3:5, 30:33], 25.2, atol=0.01)
    assert np.allclose(metres[6:], 8.0, atol=0.01)
    assert (metres[:3] == SPEC.no_return).all() and (metres[3:5, :30] == SPEC.no_return).all()


def test_the_head_refuses_nearness_of_another_batch():
    with pytest.raises(ValueError, match="nearness must be"):
        RangeHead()(torch.zeros(2, 1, 16, 28), torch.zeros(3, SPEC.beams, SPEC.azimuth, dtype=torch.uint16))


def test_range_loss_weighs_the_objects_cells():
    target = torch.zeros(1, 1, 2, 2)
    prediction = torch.tensor([[[[1.0, 0.0], [0.0, 0.0]]]])
    objects = torch.tensor([[[[True, False], [False, False]]]])
    assert range_loss(prediction, target, objects, 1.0) == pytest.approx(0.25)
    assert range_loss(prediction, target, objects, 10.0) == pytest.approx(10.0 / 13.0)
    assert range_loss(prediction, target, ~objects, 10.0) == pytest.approx(1.0 / 31.0)
    with pytest.raises(ValueError, match="shapes differ"):
        range_loss(prediction, target[..., :1], objects, 10.0)


def test_ranges_to_image_values_reads_no_return_as_the_far_end():
    r = torch.tensor([0.0, 25.0, 100.0, 150.0])
    assert torch.allclose(ranges_to_image_values(r, SPEC), torch.tensor([1.0, -0.5, 1.0, 1.0]))


def _episode_lidar(env, seed: int, steps: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed)
    out = [obs["lidar"]]
    for _ in range(steps):
        obs, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
        out.append(obs["lidar"])
    return out


def test_the_env_finishes_the_lidar_with_the_bundles_range_head(range_head_bundle, layout_bundle, monkeypatch):
    """The range head reads the scene at the range map's resolution: with it the env's LiDAR moves
    from the plain decoder's, and an env that observes no LiDAR casts no range map."""
    from m4world_env.env import M4WorldEnv
    from world_model.raster import maps

    full_resolution_casts = []
    cast = maps.cast

    def counted(poses, lidar, rays, margin):
        full_resolution_casts.append(True)
        return cast(poses, lidar, rays, margin)

    monkeypatch.setattr(maps, "cast", counted)

    def env(bundle, **config):
        return M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(bundle), config=config)

    with_head = _episode_lidar(env(range_head_bundle), 0, 2)
    assert sum(full_resolution_casts) == 3  # the reset's frame and each step's decoded one
    plain = _episode_lidar(env(layout_bundle), 0, 2)
    assert all(a.shape == b.shape for a, b in zip(with_head, plain, strict=True))
    assert not any(np.array_equal(a, b) for a, b in zip(with_head, plain, strict=True))

    full_resolution_casts.clear()
    cameras_only = env(range_head_bundle, observation_keys=["cameras"])
    cameras_only.reset(seed=0)
    cameras_only.step(np.zeros(cameras_only.action_space.shape, np.float32))
    assert not any(full_resolution_casts)


def test_vector_rows_and_simulation_workers_match_the_single_env_with_a_range_head(range_head_bundle):
    from m4world_env.env import M4WorldEnv
    from m4world_env.vector import M4WorldVectorEnv

    single = [
        _episode_lidar(M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(range_head_bundle)), s, 2)
        for s in (5, 6)
    ]
    for workers in (0, 1):
        vector = M4WorldVectorEnv(
            2,
            "highway_sunny_day",
            backend="world_model",
            checkpoint=str(range_head_bundle),
            config={"workers": workers},
        )
        obs, _ = vector.reset(seed=5)
        rows = [obs["lidar"]]
        for _ in range(2):
            obs, *_ = vector.step(np.zeros(vector.action_space.shape, np.float32))
            rows.append(obs["lidar"])
        vector.close()
        for i in range(2):
            for t, frame in enumerate(rows):
                np.testing.assert_array_equal(frame[i], single[i][t], err_msg=f"workers={workers} row {i} step {t}")


def test_the_range_map_the_scene_implies_is_the_lidars_own_cast():
    """At the range map's resolution the scene's nearness is the simulator's LiDAR, quantized."""
    from m4world_env.env import M4WorldEnv
    from world_model.model.config import get_preset
    from world_model.raster.maps import nearness_levels, range_nearness_maps
    from world_model.train.range_head_stage import with_range_head

    env = M4WorldEnv("highway_dense_rain_dusk", backend="procedural")
    obs, _ = env.reset(seed=3)
    cfg = with_range_head(get_preset("default"))
    assert env.lidar_spec == cfg.sensors.lidar
    maps = range_nearness_maps([env._frame], cfg)
    assert maps.shape == (1, cfg.sensors.lidar.beams, cfg.sensors.lidar.azimuth)
    np.testing.assert_array_equal(maps[0], nearness_levels(obs["lidar"], cfg.sensors.lidar))
    assert (maps[0] > 0).any() and (maps[0] == 0).any()  # returns, and the sky


def test_a_range_head_leaves_the_latent_caches_key_alone():
    """The latents depend on the encoder: a VAE with a range head reads the run's cached latents."""
    from world_model.model.config import get_preset, with_layout
    from world_model.model.vae import SensorVAE
    from world_model.train.data import encoder_digest
    from world_model.train.range_head_stage import with_range_head

    cfg = with_layout(get_preset("tiny"), True)
    torch.manual_seed(0)
    plain = SensorVAE(cfg)
    headed = SensorVAE(with_range_head(cfg))
    headed.load_state_dict(plain.state_dict(), strict=False)
    with torch.no_grad():
        headed.range_head.net[0].weight.add_(1.0)
    assert encoder_digest(headed) == encoder_digest(plain)
