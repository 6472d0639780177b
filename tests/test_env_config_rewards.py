import math

import numpy as np
import pytest

from m4world_env.config import EnvConfig, InvalidOptionError, RewardConfig, UnknownOptionError
from m4world_env.metrics import EpisodeMetrics, time_to_collision
from m4world_env.rewards import combine_reward, reward_terms
from world_model import Box3D, EgoState, MapGeometry, SceneFrame, SceneObject


def test_config_defaults_and_nested_override():
    cfg = EnvConfig.from_dict({"action_type": "discrete_meta", "reward": {"collision": -2.0}})
    assert cfg.action_type == "discrete_meta" and cfg.reward.collision == -2.0
    assert cfg.reward.high_speed == RewardConfig().high_speed


def test_unknown_option_names_key_and_suggests():
    with pytest.raises(UnknownOptionError, match=r"config\.acton_type.*action_type"):
        EnvConfig.from_dict({"acton_type": "continuous"})
    with pytest.raises(UnknownOptionError, match=r"config\.reward\.colision"):
        EnvConfig.from_dict({"reward": {"colision": -1}})


@pytest.mark.parametrize(
    "bad",
    [
        {"action_type": "teleport"},
        {"observation_keys": ["cameras", "radar"]},
        {"height": 0},
        {"reward": {"speed_range": (30, 20)}},
        {"model": {"dtype": "int8"}},
        {"model": {"refresh_steps": "0"}},
        {"model": {"refresh_steps": [0.5]}},
        {"model": {"refresh_steps": 0}},
        {"model": {"refresh_steps": [0], "context_refresh": False}},
        {"model": {"refresh_steps": [-1], "context_refresh": False}},
        {"model": {"sink_frames": -1}},
        {"model": {"sink_frames": 1.5}},
        {"model": {"sink_frames": True}},
        {"model": {"sink_frames": "1"}},
    ],
)
def test_invalid_values_rejected(bad):
    with pytest.raises(InvalidOptionError):
        EnvConfig.from_dict(bad)


def test_streaming_options_default_to_the_bundle_and_take_all():
    m = EnvConfig.from_dict({}).model
    assert (m.denoising_steps, m.context_refresh, m.refresh_steps, m.sink_frames) == (None, None, None, None)
    assert EnvConfig.from_dict({"model": {"refresh_steps": "all"}}).model.refresh_steps == "all"
    assert EnvConfig.from_dict({"model": {"refresh_steps": [3, -1]}}).model.refresh_steps == (3, -1)


def test_reward_terms_and_normalization():
    cfg = RewardConfig()
    best = reward_terms(
        crashed=False, speed=30.0, lane_index=2, num_lanes=3, on_road=True, progress_m=3.0, max_progress_m=3.0, cfg=cfg
    )
    assert best["high_speed"] == 1.0 and best["right_lane"] == 1.0
    assert math.isclose(combine_reward(best, cfg), 1.0)
    crash = reward_terms(
        crashed=True, speed=10.0, lane_index=0, num_lanes=3, on_road=True, progress_m=1.0, max_progress_m=3.0, cfg=cfg
    )
    assert math.isclose(combine_reward(crash, cfg), 0.0)
    off = dict(best, on_road=0.0)
    assert combine_reward(off, cfg) == 0.0  # gated by on_road like highway-env
    mid = reward_terms(
        crashed=False, speed=25.0, lane_index=0, num_lanes=3, on_road=True, progress_m=0.0, max_progress_m=3.0, cfg=cfg
    )
    assert math.isclose(mid["high_speed"], 0.5)
    assert math.isclose(combine_reward(mid, cfg), (1.0 + 0.4 * 0.5) / 1.5)


def _frame(ego_speed, obj_x, obj_speed, obj_y=0.0, yaw_rate=0.0, obj_velocity=None):
    velocity = obj_velocity if obj_velocity is not None else (obj_speed, 0.0)
    obj = SceneObject("v", "car", Box3D((obj_x, obj_y, 0.8), (4.0, 2.0, 1.6), 0.0), velocity=velocity)
    return SceneFrame(
        time=0,
        frame_index=0,
        ego=EgoState(0.0, 0.0, 0.0, speed=ego_speed, size=(4.0, 2.0, 1.6), yaw_rate=yaw_rate),
        objects=(obj,),
        map=MapGeometry(),
    )


def test_time_to_collision():
    # gap = 24 - 2 - 2 = 20 m, closing 10 m/s -> 2 s
    assert math.isclose(time_to_collision(_frame(20.0, 24.0, 10.0)), 2.0)
    assert time_to_collision(_frame(10.0, 24.0, 20.0)) == math.inf  # opening
    assert time_to_collision(_frame(20.0, 24.0, 10.0, obj_y=4.0)) == math.inf  # other lane
    assert time_to_collision(_frame(20.0, -24.0, 0.0)) == math.inf  # behind


@pytest.mark.parametrize("turn", [1.0, -1.0])
def test_time_to_collision_follows_the_turning_path(turn):
    """Ego at 10 m/s turning at 0.5 rad/s: a circle of radius 20 m about (0, 20 turn)."""
    r, phi = 20.0, 1.0  # a stopped car 1 rad (20 m of arc) along the path
    x, y = r * math.sin(phi), turn * r * (1 - math.cos(phi))
    on_path = _frame(10.0, x, 0.0, obj_y=y, yaw_rate=0.5 * turn)
    assert math.isclose(time_to_collision(on_path), (r * phi - 2 - 2) / 10.0)  # gap along the arc / closing
    # Without the turn the same car is 9 m aside (no TTC); a car straight ahead is off the turning path.
    assert time_to_collision(_frame(10.0, x, 0.0, obj_y=y)) == math.inf
    assert time_to_collision(_frame(10.0, 15.0, 0.0, yaw_rate=0.5 * turn)) == math.inf
    # A car driving along the path ahead at 6 m/s (velocity tangent to the circle there) closes at 4 m/s.
    tangent = (math.cos(phi), turn * math.sin(phi))
    moving = _frame(10.0, x, 0.0, obj_y=y, yaw_rate=0.5 * turn, obj_velocity=(6 * tangent[0], 6 * tangent[1]))
    assert math.isclose(time_to_collision(moving), (r * phi - 4) / 4.0)


def test_episode_metrics_pdms():
    m = EpisodeMetrics(dt=0.1, reference_speed=30.0)
    for i in range(11):
        fr = SceneFrame(
            time=i * 0.1,
            frame_index=i,
            ego=EgoState(x=3.0 * i, y=0.0, yaw=0.0, speed=30.0),
            objects=(),
            map=MapGeometry(),
        )
        m.add_frame(fr)
        if i:
            m.add_step(1.0, crashed=False, on_road=True)
    s = m.summary()
    assert math.isclose(s["progress"], 1.0) and s["comfort"] == 1.0 and math.isclose(s["pdms"], 1.0)
    m.add_step(0.0, crashed=True, on_road=True)
    assert m.summary()["pdms"] == 0.0 and m.summary()["collision"] == 1.0
    hard = EpisodeMetrics(dt=0.1)
    for i, v in enumerate([30.0, 29.0, 20.0]):  # -90 m/s^2 braking
        hard.add_frame(
            SceneFrame(time=i * 0.1, frame_index=i, ego=EgoState(0.0, 0.0, 0.0, speed=v), objects=(), map=MapGeometry())
        )
    assert hard.summary()["comfort"] == 0.0 and np.isclose(hard.lon_accel_min, -90.0)
