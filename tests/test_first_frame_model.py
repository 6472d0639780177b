"""A bundle's one-step first-frame model: where it draws a reset's first frame, where the reference
model still does, batched resets row for row, the env's setting, and a mismatched component."""

from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401
from tests.model_fixtures import make_frames, tiny_conditions
from world_model.bundle import CheckpointError, load_bundle_files, save_bundle
from world_model.model.config import ModelConfig
from world_model.model.reference import ONE_STEP, ReferenceGenerator
from world_model.rollout.runtime import load_world_model


@pytest.fixture(scope="module")
def wm(first_frame_bundle):
    return load_world_model(first_frame_bundle)


def _cond(wm, batch: int = 1):
    return tiny_conditions(wm.cfg, 1, batch=batch).frames(0, 1)


def test_a_first_frame_from_controls_is_one_step_of_the_first_frame_model(wm):
    cond, frame = _cond(wm), make_frames(wm.cfg, 1)[0]
    one_step = ReferenceGenerator(wm.first_frame, wm.vae).sample(cond, seed=3, sampler=ONE_STEP)
    torch.testing.assert_close(wm.first_latents(cond, frame, seed=3), one_step, rtol=0, atol=0)
    s = wm.streaming
    guided = wm.first_frames.sample(cond, steps=s.first_frame_steps, seed=3, guidance=s.first_frame_guidance)
    assert not torch.allclose(one_step, guided, atol=1e-3)
    wm.streaming = replace(s, one_step_first_frame=False)  # the reference model's guided steps instead
    try:
        torch.testing.assert_close(wm.first_latents(cond, frame, seed=3), guided, rtol=0, atol=0)
    finally:
        wm.streaming = s


def test_batched_first_frames_are_each_rows_own(wm):
    cond, frames = _cond(wm, batch=3), make_frames(wm.cfg, 1) * 3
    batch = wm.batch_first_latents(cond, frames, [5, 6, 7])
    for i, seed in enumerate((5, 6, 7)):
        row = wm.first_latents(cond.apply(lambda _, v, i=i: v[i : i + 1]), frames[i], seed=seed)
        torch.testing.assert_close(batch[i : i + 1], row, rtol=0, atol=0)


def test_a_first_frame_anchored_on_images_is_the_reference_models(wm):
    cond, frame = _cond(wm), make_frames(wm.cfg, 1)[0]
    s = wm.cfg.sensors
    image = {"FRONT": np.full((s.height, s.width, 3), 90, np.uint8)}
    expected = wm.first_frames.first_latents(
        cond, image, wm.streaming.first_frame_steps, 4, guidance=wm.streaming.first_frame_guidance
    )
    torch.testing.assert_close(wm.first_latents(cond, frame, image, seed=4), expected, rtol=0, atol=0)


def test_the_env_setting_picks_the_sampler_and_vector_rows_equal_single_envs(first_frame_bundle):
    def first_obs(**model):
        env = gym.make("M4World-v0", backend="world_model", checkpoint=str(first_frame_bundle), config={"model": model})
        obs, _ = env.reset(seed=2)
        env.close()
        return obs

    one_step, guided = first_obs(), first_obs(one_step_first_frame=False)
    assert not np.array_equal(one_step["cameras"], guided["cameras"])
    from m4world_env.vector import M4WorldVectorEnv

    envs = M4WorldVectorEnv(num_envs=2, backend="world_model", checkpoint=str(first_frame_bundle))
    obs, _ = envs.reset(seed=2)  # sub-env i is seeded 2 + i
    envs.close()
    np.testing.assert_array_equal(obs["cameras"][0], one_step["cameras"])


def test_a_first_frame_model_of_another_config_is_refused_and_of_the_same_loads(first_frame_bundle, tmp_path):
    files = load_bundle_files(first_frame_bundle)
    other = dict(files.component_config("reference"))
    other["dit"] = {**other["dit"], "depth": other["dit"]["depth"] + 1}
    configs = {"reference": files.component_config("reference"), "first_frame": other}
    bad = save_bundle(tmp_path / "bad", files.model_config, files.tensors, component_configs=configs)
    with pytest.raises(CheckpointError, match="first-frame model's config differs"):
        load_world_model(bad)
    same = dict(files.component_config("reference"))
    same["layout"] = {k: v for k, v in same["layout"].items() if k != "range_head"}  # the default, left out
    configs["first_frame"] = same
    assert load_world_model(
        save_bundle(tmp_path / "same", files.model_config, files.tensors, component_configs=configs)
    )


def test_a_run_seeded_from_the_bundle_holds_its_first_frame_model(first_frame_bundle, tmp_path):
    from world_model.train import load_teacher
    from world_model.train.exports import EXPORT
    from world_model.train.seed_run import seed_run

    assert "first_frame" in seed_run(first_frame_bundle, tmp_path / "run")
    seeded = load_teacher(tmp_path / "run" / "first_frame" / EXPORT)
    files = load_bundle_files(first_frame_bundle)
    assert seeded.cfg == ModelConfig.from_dict(files.component_config("first_frame"))
    for name, tensor in seeded.state_dict().items():
        torch.testing.assert_close(tensor, files.tensors["first_frame"][name].float())
