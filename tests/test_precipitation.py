"""The world model's rain and snow: the simulator's streaks and flakes of each frame, blended over the
decoded cameras as the simulator blends them over its own."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.model_fixtures import make_frames, make_sensors
from world_model.model import HashTextEncoder, SensorVAE, build_condition_arrays, get_preset
from world_model.model.conditions import ConditionOptions, Conditions
from world_model.model.config import with_layout
from world_model.model.sampler import latents_to_observations
from world_model.raster.maps import SceneRaster, camera_precipitation
from world_model.scene import ScenePrompt
from world_model.sim.config import SimConfig
from world_model.sim.lighting import lighting_for
from world_model.sim.precipitation import Overlay, blend, precipitation_rgb


def _in_weather(frames, weather: str, time_of_day: str = "dusk"):
    prompt = ScenePrompt(text=f"a highway in {weather}", weather=weather, time_of_day=time_of_day)
    return [replace(f, prompt=prompt, scenario="precipitation_test") for f in frames]


def test_each_frame_gets_the_simulators_streaks_and_colour_where_it_rains_or_snows():
    cfg = with_layout(get_preset("tiny"), True)
    s = cfg.sensors
    frames = make_frames(cfg, 3)
    for weather in ("rain", "snow"):
        wet = _in_weather(frames, weather)
        alpha, rgb = camera_precipitation(wet, cfg)
        assert alpha.shape == (3, s.num_cameras, s.height, s.width) and alpha.dtype == np.uint8
        lighting = lighting_for(wet[0].prompt)
        overlay = Overlay(weather, s.height, s.width, SimConfig())
        for t, frame in enumerate(wet):
            assert np.array_equal(alpha[t].reshape(-1, s.width), overlay.alpha(frame, s.num_cameras))
            assert np.array_equal(rgb[t], precipitation_rgb(lighting))
        assert 0 < (alpha > 0).mean() < 0.5
        assert not np.array_equal(alpha[0], alpha[1]), "the streaks move from frame to frame"
        skipped, _ = camera_precipitation(wet, cfg, labeled=[True, False, True])
        assert not skipped[1].any() and np.array_equal(skipped[2], alpha[2])
    clear, clear_rgb = camera_precipitation(_in_weather(frames, "sunny", "day"), cfg)
    assert not clear.any() and not clear_rgb.any()
    plain, _ = camera_precipitation(frames, get_preset("tiny"))
    assert plain.shape == (3, s.num_cameras, 0, 0)


def test_the_conditions_carry_it_for_decoded_cameras_only():
    cfg = with_layout(get_preset("tiny"), True)
    frames = _in_weather(make_frames(cfg, 2), "snow")
    _, _, bev = make_sensors(cfg, 2)
    text = HashTextEncoder(cfg.text.dim)
    raster = SceneRaster(cfg)
    arrays = build_condition_arrays(frames, bev, cfg, text, ConditionOptions(raster=raster))
    assert arrays.precipitation.any() and arrays.precipitation_rgb.any()
    assert set(raster.overlays) == {("snow", cfg.sensors.height, cfg.sensors.width)}
    lidar_only = ConditionOptions(raster=raster, sensors=replace(ConditionOptions().sensors, cameras=False))
    assert not build_condition_arrays(frames, bev, cfg, text, lidar_only).precipitation.any()


def test_the_decoded_cameras_get_it_blended_as_the_simulator_blends_it():
    cfg = with_layout(get_preset("tiny"), True)
    frames = _in_weather(make_frames(cfg, 2), "rain")
    _, _, bev = make_sensors(cfg, 2)
    arrays = build_condition_arrays(frames, bev, cfg, HashTextEncoder(cfg.text.dim))
    arrays.precipitation[0] = 0  # a frame without rain keeps its pixels
    cond = Conditions.collate([arrays])
    torch.manual_seed(0)
    vae = SensorVAE(cfg).eval()
    s = cfg.sensors
    latents = torch.randn(1, 2, s.num_views, cfg.vae.latent_channels, *cfg.latent_hw)
    inputs = cond.decoder_inputs()
    dry = latents_to_observations(vae, latents, s.lidar, **{**inputs, "precipitation": None})[0]
    wet = latents_to_observations(vae, latents, s.lidar, **inputs)[0]
    assert np.array_equal(wet[0].cameras, dry[0].cameras)
    alpha = arrays.precipitation[1].reshape(-1, s.width)
    expected = blend(dry[1].cameras.reshape(-1, s.width, 3), alpha, arrays.precipitation_rgb[1])
    assert np.array_equal(wet[1].cameras, expected.reshape(dry[1].cameras.shape))
    assert not np.array_equal(wet[1].cameras, dry[1].cameras)
    assert np.array_equal(wet[1].lidar, dry[1].lidar)


@pytest.mark.parametrize("kind", ["hail", ""])
def test_an_unknown_precipitation_kind_is_refused(kind):
    with pytest.raises(ValueError, match="precipitation kind must be 'rain' or 'snow'"):
        Overlay(kind, 8, 8, SimConfig())
