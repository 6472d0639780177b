"""The Gymnasium face of the project on the procedural backend."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from gymnasium.utils.env_checker import check_env

import m4world_env  # noqa: F401
from m4world_env.config import InvalidOptionError, UnknownOptionError
from m4world_env.env import ActionError, M4WorldEnv
from m4world_env.scenario import ScenarioError

SMALL = {"height": 32, "width": 56}


def make(**kw):
    kw.setdefault("scenario", "highway_sunny_day")
    kw.setdefault("config", dict(SMALL))
    return gym.make("M4World-v0", **kw)


def test_gymnasium_check_env_passes_including_determinism():
    env = make(config={**SMALL, "observation_keys": ["cameras", "lidar", "bev", "state"]})
    check_env(env.unwrapped, skip_render_check=True)
    env_d = make(config={**SMALL, "action_type": "discrete_meta"})
    check_env(env_d.unwrapped, skip_render_check=True)


def test_sb3_check_env_passes():
    sb3_env_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env = M4WorldEnv("highway_sunny_day", config={**SMALL, "observation_keys": ["cameras", "state"]})
    sb3_env_checker.check_env(env, warn=True, skip_render_check=True)


def test_observation_layout_and_info():
    env = make(config={**SMALL, "observation_keys": ["cameras", "lidar", "bev", "state"]})
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    assert obs["cameras"].shape == (6, 32, 56, 3) and obs["cameras"].dtype == np.uint8
    assert obs["lidar"].shape == (32, 1024) and obs["lidar"].dtype == np.float32
    assert env.unwrapped.camera_names == ("FRONT_LEFT", "FRONT", "FRONT_RIGHT", "BACK_RIGHT", "BACK", "BACK_LEFT")
    obs, reward, terminated, truncated, info = env.step(np.array([0.5, 0.0], np.float32))
    assert 0.0 <= reward <= 1.0
    for key in ("time", "speed", "crashed", "on_road", "rewards", "episode_metrics"):
        assert key in info
    assert set(info["rewards"]) == {"collision", "high_speed", "right_lane", "on_road", "progress"}
    assert info["time"] > 0


def test_same_seed_same_observations_different_seed_differs():
    def rollout(seed):
        env = make(config={**SMALL, "observation_keys": ["cameras", "lidar", "state"]})
        obs, _ = env.reset(seed=seed)
        out = [obs]
        for a in ([0.2, 0.0], [0.0, 0.05], [-0.3, 0.0]):
            out.append(env.step(np.array(a, np.float32))[0])
        return out

    a, b, c = rollout(7), rollout(7), rollout(8)
    for oa, ob in zip(a, b, strict=True):
        for k in oa:
            assert np.array_equal(oa[k], ob[k]), k
    assert not np.array_equal(a[-1]["state"], c[-1]["state"])


@pytest.mark.parametrize(
    "action, match",
    [
        ([np.nan, 0.0], "NaN"),
        ([np.inf, 0.0], "NaN or inf"),
        ([1.5, 0.0], r"\[-1, 1\]"),
        ([0.1, 0.2, 0.3], "shape"),
        ("fast", "numeric"),
    ],
)
def test_bad_continuous_actions_refused_env_stays_usable(action, match):
    env = make()
    env.reset(seed=0)
    with pytest.raises(ActionError, match=match):
        env.step(action)
    obs, *_ = env.step(np.zeros(2, np.float32))  # still usable
    assert obs["cameras"].shape[0] == 6


def test_bad_discrete_actions_refused():
    env = make(config={**SMALL, "action_type": "discrete_meta"})
    env.reset(seed=0)
    for bad in (5, -1, 1.5, [1, 2]):
        with pytest.raises(ActionError):
            env.step(bad)
    env.step(1)


def test_bad_construction_and_options():
    with pytest.raises(ScenarioError, match="no_such_scenario"):
        make(scenario="no_such_scenario")
    with pytest.raises(UnknownOptionError, match="obsrvation_keys"):
        make(config={"obsrvation_keys": ["cameras"]})
    with pytest.raises(InvalidOptionError, match="backend"):
        make(backend="unreal")
    with pytest.raises(InvalidOptionError, match="checkpoint"):
        make(checkpoint="/nonexistent.safetensors")
    env = make()
    with pytest.raises(UnknownOptionError, match="referense"):
        env.reset(seed=0, options={"referense": None})


@pytest.mark.parametrize(
    "config,match",
    [
        ({"height": "abc"}, "config.height must be an integer"),
        ({"reward": {"collision": "big"}}, "config.reward.collision must be a finite number"),
        ({"reward": {"high_speed": float("nan")}}, "config.reward.high_speed must be a finite number"),
        ({"reward": {"speed_range": 5}}, "speed_range must be two finite numbers"),
        ({"reward": {"speed_range": [1, 2, 3]}}, "speed_range must be two finite numbers"),
        ({"offroad_terminal": "no"}, "config.offroad_terminal must be True or False"),
        ({"model": {"context_refresh": "no"}}, "config.model.context_refresh must be True or False"),
        ({"model": {"denoising_steps": 2.5}}, "config.model.denoising_steps must be an integer"),
    ],
)
def test_option_values_of_the_wrong_type_are_refused_by_name(config, match):
    with pytest.raises(InvalidOptionError, match=match):
        make(config={**SMALL, **config})


def test_step_before_reset_and_after_termination():
    env = M4WorldEnv("stopped_vehicle_snow", config=SMALL)
    with pytest.raises(ResetNeeded):
        env.step(np.zeros(2, np.float32))
    with pytest.raises(ResetNeeded):
        env.scene_frame  # noqa: B018  (the property raises)
    env.reset(seed=0)
    assert env.scene_frame.time == 0.0
    terminated = truncated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))  # full throttle
        assert env.scene_frame.time == pytest.approx(info["time"])  # the scene the observation shows
    with pytest.raises(ResetNeeded):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=1)
    env.step(np.zeros(2, np.float32))


def test_crash_terminates_with_collision_reward():
    env = M4WorldEnv("stopped_vehicle_snow", config=SMALL)
    env.reset(seed=0)
    for _ in range(400):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated and info["crashed"] and info["rewards"]["collision"] == 1.0
    assert info["episode_metrics"]["collision"] == 1.0 and info["episode_metrics"]["pdms"] == 0.0


def test_reaching_the_end_of_the_road_network_truncates_instead_of_going_off_road():
    """The roundabout's exit lane ends 150 m out; an IDM ego gets there before the 30 s are up."""
    from m4world_env.policies import IDMAutopilot

    env = M4WorldEnv("roundabout_fog", config={**SMALL, "observation_keys": ["state"]})
    env.reset(seed=0)
    pilot = IDMAutopilot(seed=0)
    terminated = truncated = False
    while not (terminated or truncated):
        _, reward, terminated, truncated, info = env.step(pilot(env))
    assert truncated and not terminated and info["end_of_road"] and info["on_road"]
    assert info["time"] < env.unwrapped.scenario.duration
    assert info["episode_metrics"]["off_road"] == 0.0 and reward > 0


def test_progress_is_relative_to_the_road_speed_limit():
    """Driving at a 12 m/s roundabout's limit earns the same full progress as 30 m/s on a motorway."""
    from m4world_env.policies import IDMAutopilot

    for scenario in ("roundabout_fog", "empty_highway"):
        env = M4WorldEnv(scenario, config={**SMALL, "observation_keys": ["state"]})
        env.reset(seed=0)
        limit = env.scenario.road.speed_limit
        pilot = IDMAutopilot(seed=0)
        for _ in range(10):
            _, _, _, _, info = env.step(pilot(env))
        speed_fraction = info["speed"] / limit
        assert info["rewards"]["progress"] == pytest.approx(min(speed_fraction, 1.0), abs=0.1)
        assert info["episode_metrics"]["progress"] > 0.5


def test_render_mosaic():
    env = make(render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[0] > 32 and img.shape[1] > 56 * 3


def test_rgb_array_list_renders_every_sensor_frame_once():
    single, every = make(render_mode="rgb_array"), make(render_mode="rgb_array_list")
    assert every.metadata["render_fps"] == 10 and single.metadata["render_fps"] == 5  # sensor vs policy rate
    single.reset(seed=0)
    every.reset(seed=0)
    assert len(every.render()) == 1 and every.render() == []  # the reset frame, then nothing new
    for _ in range(2):
        single.step(np.zeros(2, np.float32))
        every.step(np.zeros(2, np.float32))
    frames = every.render()
    assert len(frames) == 4 and np.array_equal(frames[-1], single.render())
    assert not np.array_equal(frames[-2], frames[-1])


@pytest.mark.parametrize("render_mode", ["rgb_array", "rgb_array_list"])
def test_record_video_writes_the_mosaic_at_the_render_rate(tmp_path, render_mode):
    """gymnasium's RecordVideo on rgb_array: one frame per step at the policy frequency; ours on
    rgb_array_list: every sensor frame at the sensor frequency."""
    pytest.importorskip("moviepy")  # the `video` extra
    import imageio.v3 as iio

    from m4world_env.wrappers import RecordVideo

    wrapper = gym.wrappers.RecordVideo if render_mode == "rgb_array" else RecordVideo
    env = wrapper(make(render_mode=render_mode), str(tmp_path / "videos"), episode_trigger=lambda e: True)
    env.reset(seed=0)
    for _ in range(6):
        env.step(np.zeros(2, np.float32))
    env.close()
    (video,) = (tmp_path / "videos").glob("*.mp4")
    frames = iio.imread(video)
    per_step = env.unwrapped.scenario.frames_per_step if render_mode == "rgb_array_list" else 1
    assert frames.shape[0] == 1 + 6 * per_step  # the reset frame, then each step's
    assert iio.immeta(video)["fps"] == env.metadata["render_fps"]


def test_object_manipulation_reflected_next_step():
    env = M4WorldEnv("empty_highway", config={**SMALL, "observation_keys": ["cameras", "state"]})
    obs0, _ = env.reset(seed=0)
    before, *_ = env.step(np.zeros(2, np.float32))
    ego = env.bridge.ego
    tid = env.insert_object(
        {
            "id": "inserted",
            "category": "bus",
            "color": "yellow",
            "description": "a yellow school bus",
            "track": {"kind": "static", "x": ego.x + 25.0, "y": ego.y, "yaw": ego.yaw},
        }
    )
    after, *_ = env.step(np.zeros(2, np.float32))
    front = env.camera_names.index("FRONT")
    assert np.abs(after["cameras"][front].astype(int) - before["cameras"][front].astype(int)).mean() > 2.0
    assert after["state"][1, 0] == 1.0  # an object is now present in the state
    env.edit_object(tid, color="blue")
    edited, *_ = env.step(np.zeros(2, np.float32))
    mean_before = after["cameras"][front].reshape(-1, 3).mean(0)
    mean_after = edited["cameras"][front].reshape(-1, 3).mean(0)
    assert mean_after[2] - mean_after[0] > mean_before[2] - mean_before[0]  # bluer
    env.remove_object(tid)
    removed, *_ = env.step(np.zeros(2, np.float32))
    assert removed["state"][1, 0] == 0.0


def test_a_bad_action_in_one_sub_env_leaves_every_sub_env_as_it_was():
    venv = gym.make_vec(
        "M4World-v0", num_envs=2, vectorization_mode="vector_entry_point", scenario="merge_cut_in", config=SMALL
    )
    venv.reset(seed=5)
    with pytest.raises(ActionError, match="sub-env 1"):
        venv.step(np.array([[0.1, 0.0], [0.0, np.nan]], np.float32))
    with pytest.raises(InvalidOptionError, match="one per sub-env"):
        venv.step([[0.1, 0.0], [0.0]])
    *_, info = venv.step(np.zeros((2, 2), np.float32))
    assert np.allclose(info["time"], info["time"][0])  # no sub-env advanced by the refused steps


def test_a_failed_reset_leaves_no_half_reset_episode():
    env = make(config={**SMALL, "observation_keys": ["state"]})
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.array([0.5, 0.0], np.float32))
    h, w = SMALL["height"], SMALL["width"]
    with pytest.raises(ValueError, match="world_model"):  # the procedural backend takes no reference
        env.reset(seed=1, options={"reference": {"FRONT": np.zeros((h, w, 3), np.uint8)}})
    with pytest.raises(ResetNeeded, match="last reset failed"):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=1)
    *_, info = env.step(np.zeros(2, np.float32))
    assert info["episode_metrics"]["steps"] == 1 and info["time"] == pytest.approx(0.2)


def test_vector_env_equals_single_envs_and_autoreset():
    n, seed = 3, 11
    cfg = {**SMALL, "observation_keys": ["cameras", "lidar", "state"]}
    venv = gym.make_vec(
        "M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", scenario="merge_cut_in", config=cfg
    )
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    singles = [make(scenario="merge_cut_in", config=cfg) for _ in range(n)]
    vobs, _ = venv.reset(seed=seed)
    for i, env in enumerate(singles):
        env.reset(seed=seed + i)
    rng = np.random.default_rng(0)
    for _ in range(4):
        actions = rng.uniform(-0.5, 0.5, size=(n, 2)).astype(np.float32)
        vobs, vrew, vterm, vtrunc, _ = venv.step(actions)
        sres = [env.step(a) for env, a in zip(singles, actions, strict=True)]
        for i, (o, r, *_rest) in enumerate(sres):
            for k in o:
                assert np.array_equal(vobs[k][i], o[k]), (i, k)
            assert vrew[i] == pytest.approx(r)
    venv.close()


def test_vector_env_autoreset_next_step():
    venv = gym.make_vec(
        "M4World-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        scenario="stopped_vehicle_snow",
        config={**SMALL, "observation_keys": ["state"]},
    )
    venv.reset(seed=0)
    ended = None
    for _ in range(400):
        _, rew, term, trunc, _ = venv.step(np.tile([1.0, 0.0], (2, 1)).astype(np.float32))
        if ended is not None:
            # the step after an episode ended is a reset: reward 0, flags False
            assert rew[ended] == 0.0 and not term[ended] and not trunc[ended]
            break
        if (term | trunc).any():
            ended = int(np.argmax(term | trunc))
    assert ended is not None
