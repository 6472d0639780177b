"""Train/serve parity: the world-model env builds, for a scene, exactly the condition arrays that
training builds from a recording of that scene (every field, reference crops and layout included)."""

from dataclasses import fields

import numpy as np
import pytest
import torch
from gymnasium.utils import seeding

from m4world_env.env import M4WorldEnv
from m4world_env.policies import IDMAutopilot
from m4world_env.recorder import RecordConfig, record_episode
from m4world_env.scenario import load_scenario
from world_model.data import Clip, read_clip, write_clip
from world_model.model.conditions import ConditionArrays
from world_model.raster.classes import CLASS_PLANE, ROAD, VEHICLE
from world_model.raster.maps import camera_labels, camera_precipitation, lidar_nearness_maps
from world_model.rollout.runtime import WorldModel
from world_model.sim.labels import LabelRasterizer
from world_model.train.data import LatentWindows

# A scene where a crop is cut at reset and another one mid-rollout (a car that comes close at 1 s).
SCENARIO, ENV_SEED, DURATION_S = "highway_dense_rain_dusk", 1, 2.0


def _env_rollout(checkpoint, scenario) -> tuple[list, list[ConditionArrays], WorldModel]:
    """Drive the world-model env with the autopilot; return its frames and the arrays it built."""
    env = M4WorldEnv(
        scenario, backend="world_model", checkpoint=str(checkpoint), config={"action_type": "discrete_meta"}
    )
    wm = env.backend.wm
    built: list[ConditionArrays] = []
    original = wm.conditions.arrays

    def spy(*args, **kwargs):
        built.append(original(*args, **kwargs))
        return built[-1]

    wm.conditions.arrays = spy
    env.reset(seed=ENV_SEED)
    frames = [env._frame]
    policy = IDMAutopilot(seed=_bridge_seed())
    truncated = terminated = False
    while not (truncated or terminated):
        chunk = env.advance(policy(env))
        (obs,) = env.backend.step([chunk])
        _, _, terminated, truncated, _ = env.finish_step(chunk, obs)
        frames.extend(chunk)
    return frames, built, wm


def _bridge_seed() -> int:
    """The traffic seed ``env.reset(seed=ENV_SEED)`` draws (the recorder is given the same)."""
    rng, _ = seeding.np_random(ENV_SEED)
    return int(rng.integers(0, 2**31 - 1))


@pytest.mark.parametrize("layout", [False, True])
def test_env_condition_arrays_equal_the_recorded_clips(tiny_bundle, layout_bundle, tmp_path, layout):
    checkpoint = layout_bundle if layout else tiny_bundle
    scenario = load_scenario(SCENARIO).model_copy(update={"duration": DURATION_S})
    env_frames, env_arrays, wm = _env_rollout(checkpoint, scenario)
    cfg = wm.cfg
    rec = RecordConfig(
        scenarios=[scenario.name],
        randomize=False,
        height=cfg.sensors.height,
        width=cfg.sensors.width,
        lidar=cfg.sensors.lidar,
        bev=cfg.sensors.bev,
        action_type="discrete_meta",
    )
    frames, cams, lidar, bev, crops = record_episode(scenario, _bridge_seed(), rec)
    assert [f.to_dict() for f in frames] == [f.to_dict() for f in env_frames]  # the same scene
    assert 0 in crops.since.values() and max(crops.since.values()) > 0, "crops at reset and later are covered"
    write_clip(tmp_path, Clip("clip", frames, cams, lidar, bev, crops.crops, {"crop_since": crops.since}))
    clip = read_clip(tmp_path, "clip")

    # The training data path (the encoders are pure functions of content, shared for brevity).
    latents = [torch.zeros(cfg.latent_shape(clip.num_frames))]
    windows = LatentWindows([clip], latents, cfg, wm.text, wm.image)
    _, train = windows.window(0, 0, clip.num_frames)

    # The env built the first frame's arrays at reset, then one chunk per step.
    chunk = cfg.clip.chunk_frames
    starts = [0] + list(range(1, clip.num_frames, chunk))
    assert len(env_arrays) == len(starts)
    # The DiTs' windows leave out the decoder's label maps; the decoder stage renders them from the
    # clip's frames. The env renders them only for the frames it decodes.
    assert train.labels.shape[3:] == (0, 0) and train.lidar_nearness.shape[1:] == (0, 0)
    raster = LabelRasterizer()
    labels = np.stack([raster.maps(f, f.rig, cfg.sensors.height, cfg.sensors.width) for f in clip.frames])
    nearness = lidar_nearness_maps(clip.frames, cfg)
    rain, rain_rgb = camera_precipitation(clip.frames, cfg)
    for start, got in zip(starts, env_arrays, strict=True):
        want = train.frames(start, start + got.num_frames)
        for f in fields(ConditionArrays):
            if f.name in ("labels", "lidar_nearness", "precipitation", "precipitation_rgb"):
                continue
            a, b = getattr(got, f.name), getattr(want, f.name)
            assert a.shape == b.shape and np.allclose(a, b, atol=1e-5), f"{f.name} differs at frame {start}"
        if layout:
            for t in range(start, start + got.num_frames):
                decoded = t % scenario.frames_per_step == 0  # the first frame, then each step's last
                want_labels = labels[t] if decoded else camera_labels([clip.frames[t]], cfg, labeled=[False])[0]
                assert np.array_equal(got.labels[t - start], want_labels), f"labels differ at {t}"
                want_near = nearness[t] if decoded else np.zeros_like(nearness[t])
                assert np.array_equal(got.lidar_nearness[t - start], want_near), f"nearness differs at {t}"
                want_rain = rain[t] if decoded else np.zeros_like(rain[t])
                assert np.array_equal(got.precipitation[t - start], want_rain), f"rain differs at {t}"
                assert np.array_equal(got.precipitation_rgb[t - start], rain_rgb[t] if decoded else np.zeros(3))
        else:
            assert got.labels.shape[3:] == (0, 0) and got.lidar_nearness.shape[1:] == (0, 0)
            assert got.precipitation.shape[2:] == (0, 0)
    has_image = np.concatenate([a.obj_has_image for a in env_arrays])
    assert has_image[0].any()  # crops reached the conditions from the first frame
    if layout:
        assert train.layout.shape[2] == cfg.layout.channels and train.layout[:, :, 0].sum() > 0  # road seen
        assert nearness.shape[1:] == (cfg.sensors.height, cfg.sensors.width) and (nearness > 0).mean() > 0.3
        assert (labels[:, :, CLASS_PLANE] == ROAD).any() and (labels[:, :, CLASS_PLANE] == VEHICLE).any()
        assert rain.any(), "the scenario's rain reaches the decoded cameras"


def test_each_decoded_frame_has_its_label_map(layout_bundle):
    """rgb_array_list decodes every frame of a step, the others only its last: each rollout gets
    the label maps it draws, and refuses to decode a frame whose map was left out."""
    scenario = load_scenario(SCENARIO).model_copy(update={"duration": DURATION_S})
    env = M4WorldEnv(scenario, backend="world_model", checkpoint=str(layout_bundle), render_mode="rgb_array_list")
    env.reset(seed=0)
    env.step(np.zeros(2, np.float32))
    assert len(env.render()) == 1 + scenario.frames_per_step
    chunk = env.advance(np.zeros(2, np.float32))
    arrays = env.backend.wm.conditions.chunk_arrays(chunk, chunk[0], every_frame=False)
    with pytest.raises(RuntimeError, match="no label map"):
        env.backend.rollouts.step_arrays([arrays])
