"""A world-model env decodes only the sensors it observes or renders (SensorSelection), and what it
decodes is bit for bit what an env observing every sensor decodes: single env, vector env and
simulation workers, reset and step."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401
from m4world_env.env import M4WorldEnv, observation_dict
from world_model.observation import SensorNotDecoded
from world_model.raster.classes import CLASS_PLANE, NO_LABEL
from world_model.sim import mosaic

SCENARIO = "highway_sunny_day"
ACTIONS = np.array([[0.3, 0.0], [-0.5, 0.2]], np.float32)
BOTH = ["cameras", "lidar"]
GATE_NOISE = 0.5  # enough for the label maps to move pixels and ranges


@pytest.fixture(scope="module")
def drawing_bundle(layout_bundle, tmp_path_factory):
    """``layout_bundle`` with noise on its decoder's label modulations and nearness gate, which an
    untrained decoder starts at zero (drawing nothing): here the camera label maps move the
    cameras and the nearness maps the LiDAR, so a decode that lost or mixed up a map shows."""
    from world_model.bundle import load_bundle_files, save_bundle
    from world_model.model.vae import LABEL_DECODER_WEIGHTS

    files = load_bundle_files(layout_bundle)
    gen = torch.Generator().manual_seed(0)
    vae = dict(files.tensors["vae"])
    for name, value in vae.items():
        if name.startswith(LABEL_DECODER_WEIGHTS):
            vae[name] = value + GATE_NOISE * torch.randn(value.shape, generator=gen)
    configs = {"reference": files.component_config("reference")}
    out = tmp_path_factory.mktemp("bundle") / "drawing"
    return save_bundle(out, files.model_config, {**files.tensors, "vae": vae}, component_configs=configs)


@pytest.fixture(autouse=True)
def one_thread():
    """Every env of a comparison at one torch thread count (the decoder's reductions split by thread)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _single(bundle, keys, render_mode=None):
    config = {"observation_keys": keys}
    return M4WorldEnv(SCENARIO, backend="world_model", checkpoint=str(bundle), render_mode=render_mode, config=config)


def _episode(env, seed=3) -> list[dict]:
    """The observations of a reset and a step per action."""
    observations = [env.reset(seed=seed)[0]]
    observations += [env.step(action)[0] for action in ACTIONS]
    return observations


def _vector(bundle, keys, workers=0):
    config = {"observation_keys": keys, "workers": workers}
    return gym.make_vec(
        "M4World-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        scenario=SCENARIO,
        backend="world_model",
        checkpoint=str(bundle),
        config=config,
    )


def _vector_episode(venv, seed=3) -> list[dict]:
    observations = [venv.reset(seed=seed)[0]]
    observations += [venv.step(ACTIONS)[0] for _ in range(len(ACTIONS))]
    venv.close()
    return observations


def _assert_same(full: list[dict], partial: list[dict], key: str) -> None:
    for step, (a, b) in enumerate(zip(full, partial, strict=True)):
        assert np.array_equal(a[key], b[key]), (step, key)


def test_a_single_env_decodes_only_its_sensors_and_they_equal_the_full_envs(drawing_bundle):
    full = _episode(_single(drawing_bundle, BOTH))
    envs = {}
    for keys, absent in ((["lidar"], "cameras"), (["cameras"], "lidar")):
        env = envs[keys[0]] = _single(drawing_bundle, keys)
        partial = _episode(env)
        _assert_same(full, partial, keys[0])
        assert getattr(env._obs, absent) is None and absent not in partial[-1]  # never decoded
        with pytest.raises(SensorNotDecoded, match=f"no {absent}"):
            observation_dict((absent,), env._obs, None)
        with pytest.raises(SensorNotDecoded):
            mosaic(env._obs)
    # Only an env that decodes the cameras draws their label maps (the step's last frame's).
    drawn = {k: env.backend.rollouts.last_arrays[0].labels[-1, :, CLASS_PLANE] != NO_LABEL for k, env in envs.items()}
    assert drawn["cameras"].any() and not drawn["lidar"].any()
    state_only = _single(drawing_bundle, ["state", "bev"])
    _episode(state_only)
    assert state_only._obs.cameras is None and state_only._obs.lidar is None


def test_rendering_decodes_both_sensors_on_every_frame(drawing_bundle):
    """``rgb_array_list`` shows every sensor frame's cameras and LiDAR, whatever the keys."""
    env = _single(drawing_bundle, ["state"], render_mode="rgb_array_list")
    env.reset(seed=3)
    env.step(ACTIONS[0])
    frames = env.render()
    assert len(frames) == 1 + env.scenario.frames_per_step and all(f.ndim == 3 for f in frames)


def test_a_vector_env_and_its_workers_decode_only_their_sensors_bit_for_bit(drawing_bundle):
    full = _vector_episode(_vector(drawing_bundle, BOTH))
    lidar_only = _vector_episode(_vector(drawing_bundle, ["lidar"]))
    _assert_same(full, lidar_only, "lidar")
    assert "cameras" not in lidar_only[-1]
    with_workers = _vector(drawing_bundle, ["cameras"], workers=1)
    backend = with_workers.unwrapped.backend
    cameras_only = _vector_episode(with_workers)
    _assert_same(full, cameras_only, "cameras")
    assert not backend.sensors.lidar and backend.rollouts.sensors == backend.sensors
