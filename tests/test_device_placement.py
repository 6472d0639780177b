"""Every tensor the runtime creates lands on the model's device: the runtime, the sampler, the
reference generator and the streaming engine run with the model on ``meta`` (a stand-in for a GPU
that needs none) under :class:`tests.device_fixtures.OnDevice`."""

from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import world_model
from tests.device_fixtures import OffDeviceTensor, OnDevice
from tests.model_fixtures import make_frames, tiny_conditions
from world_model.model import MultiViewDiT, SensorVAE, get_preset
from world_model.model.reference import ReferenceGenerator, expand_teacher
from world_model.model.sampler import generate, sample_latents
from world_model.raster.crops import RecordedCrops
from world_model.rollout.batch import RolloutBatch
from world_model.rollout.conditions import RolloutConditions
from world_model.rollout.runtime import load_world_model
from world_model.streaming import REFRESH_EVERY_STEP, StreamingConfig
from world_model.student import StreamingEngine, StudentConfig

CFG = get_preset("tiny")
META = torch.device("meta")


def _on_meta(module: torch.nn.Module) -> torch.nn.Module:
    return module.to(META).eval().requires_grad_(False)


def test_the_guard_flags_a_factory_off_the_model_device_and_names_the_line():
    def forgets_the_device():
        return torch.zeros(3)

    # As if it were library code: the guard checks the factories of world_model/ and m4world_env/.
    library_file = str(Path(world_model.__file__).parent / "forgetful.py")
    forgets_the_device.__code__ = forgets_the_device.__code__.replace(co_filename=library_file)
    with OnDevice(META), pytest.raises(OffDeviceTensor, match=r"torch.zeros made a cpu tensor at .*forgets_the_device"):
        forgets_the_device()
    with OnDevice(META):
        assert torch.zeros(3, device=META).device == META
        assert torch.randn(3, generator=torch.Generator().manual_seed(0)).device.type == "cpu"  # seeded host noise


@pytest.mark.parametrize(
    "streaming",
    [
        StreamingConfig(context_refresh=False),
        StreamingConfig(context_refresh=True, refresh_steps=REFRESH_EVERY_STEP, sink_frames=1),
        StreamingConfig(context_refresh=True, refresh_steps=(2, 3), sink_frames=0),
    ],
    ids=["cache", "refresh+sink", "refresh_steps"],
)
def test_rollouts_reset_step_and_restart_on_the_model_device(tiny_bundle, streaming):
    wm = load_world_model(tiny_bundle, device="meta", dtype="float32")
    wm.student_cfg = replace(wm.student_cfg, streaming=streaming)
    frames = make_frames(wm.cfg, 9)
    chunk = wm.cfg.clip.chunk_frames
    guard = OnDevice(META)
    with guard:
        conditions = RolloutConditions(wm.conditions, 2)
        rollouts = RolloutBatch(wm, num_rollouts=2)
        crop = np.full((12, 10, 3), 90, np.uint8)  # an object's image description, encoded by the VAE
        for row in range(2):
            arrays = conditions.restart(row, frames[0], RecordedCrops({"car0": crop}))
            rollouts.start_row(row, frames[0], row, arrays)
        obs = rollouts.step_arrays([conditions.advance(row, frames[1 : 1 + chunk]) for row in range(2)])
        restarted = conditions.restart(1, frames[0], RecordedCrops())
        rollouts.start_row(1, frames[0], 5, restarted)  # one row restarts, the other continues
        again = rollouts.step_arrays([conditions.advance(0, frames[1 + chunk : 1 + 2 * chunk]), None])
    assert obs[0][0].cameras.shape == (wm.cfg.sensors.num_cameras, wm.cfg.sensors.height, wm.cfg.sensors.width, 3)
    assert again[1] is None and len(again[0]) == 1
    assert guard.host_reads > 0  # the decoded frames were read back to the host
    assert wm.student.patch_in.weight.device == META


def test_off_the_cpu_a_vector_step_decodes_its_frames_together(tiny_bundle, monkeypatch):
    # One decoder call per env launches its kernels once per env on a GPU; the CPU decodes frame
    # by frame so that a vector env's rows equal single envs bit for bit.
    from world_model.model.sampler import DECODE_FRAMES_PER_CALL

    frames = DECODE_FRAMES_PER_CALL + 2
    calls = {}
    for device in ("cpu", "meta"):
        wm = load_world_model(tiny_bundle, device=device, dtype="float32")
        latents = torch.zeros(frames, *wm.cfg.latent_shape(1), device=device)
        calls[device] = 0

        def counted(*args, device=device, decode_frames=wm.vae.decode_frames, **kwargs):
            calls[device] += 1
            return decode_frames(*args, **kwargs)

        monkeypatch.setattr(wm.vae, "decode_frames", counted)
        with OnDevice(META) if device == "meta" else nullcontext():
            obs = wm.decode(latents)
        assert len(obs) == frames
    assert calls == {"cpu": frames, "meta": 2}


def test_reference_generator_first_frames_references_and_completion_on_the_model_device():
    torch.manual_seed(0)
    vae, model = _on_meta(SensorVAE(CFG)), _on_meta(expand_teacher(MultiViewDiT(CFG)))
    gen = ReferenceGenerator(model, vae)
    cond = tiny_conditions(CFG, 2)
    front = np.zeros((CFG.sensors.height, CFG.sensors.width, 3), np.uint8)
    lidar = np.full((CFG.sensors.lidar.beams, CFG.sensors.lidar.azimuth), 10.0, np.float32)
    frames = make_frames(CFG, 2)
    with OnDevice(META):
        lat, obs = gen.first_frame(cond, steps=2)
        lat_ref, _ = gen.first_frame(cond, {"FRONT": front, "lidar": lidar}, steps=2)
        clip, _ = gen.from_first_frame(cond, {"FRONT": front}, steps=2)
        done = gen.complete_category(cond, lat, frames[:1], "car", steps=2)
        cams = np.zeros((2, CFG.sensors.num_cameras, CFG.sensors.height, CFG.sensors.width, 3), np.uint8)
        obj, _, _ = gen.complete_object(cond, frames, cams, np.stack([lidar, lidar]), "car0", steps=2)
    for out in (lat, lat_ref, clip, done, obj):
        assert out.device == META
    assert len(obs) == 1


@pytest.mark.parametrize("layout", [False, True], ids=["tokens", "layout channels"])
def test_sampler_with_guidance_on_the_model_device(layout):
    cfg = replace(CFG, layout=replace(CFG.layout, enabled=layout))
    torch.manual_seed(0)
    model, vae = _on_meta(MultiViewDiT(cfg)), _on_meta(SensorVAE(cfg))
    assert cfg.sampler.camera_cfg_scale != 1.0  # the guided path: conditional + unconditional batch
    cond = tiny_conditions(cfg, 2, batch=2)
    with OnDevice(META):
        lat = sample_latents(model, cond, torch.Generator().manual_seed(0), replace(cfg.sampler, steps=2))
        obs = generate(model, vae, cond, torch.Generator().manual_seed(0), replace(cfg.sampler, steps=2))
    assert lat.device == META and len(obs) == 2 and len(obs[0]) == 2


def test_streaming_engine_start_step_restart_on_the_model_device():
    student_cfg = CFG.for_student()
    torch.manual_seed(0)
    model = _on_meta(MultiViewDiT(student_cfg))
    c = student_cfg.clip.chunk_frames
    cond = tiny_conditions(student_cfg, 1 + 2 * c, batch=2)
    first = torch.zeros(2, 1, *student_cfg.latent_shape(1)[1:])
    with OnDevice(META):
        engine = StreamingEngine(model, StudentConfig(), generator=torch.Generator())
        engine.start(first, cond.frames(0, 1))
        out = engine.step(cond.frames(1, 1 + c))
        engine.start_rows([0], first[:1], cond.frames(0, 1).apply(lambda _, v: v[:1]))
        out = engine.step(cond.frames(1 + c, 1 + 2 * c))
    assert out.device == META and engine.cache.layers[0][0].device == META


@pytest.mark.parametrize("bundle", ["tiny_bundle", "layout_bundle"])
def test_the_env_and_a_vector_env_step_with_the_model_on_the_device(bundle, request, monkeypatch):
    import gymnasium as gym

    tiny_bundle = request.getfixturevalue(bundle)  # layout: the decoder reads label maps and style

    # A user's config.model.device is cpu, cuda[:N] or auto; meta (no values) is this test's stand-in.
    monkeypatch.setattr("m4world_env.config.DEVICE_TYPES", ("cpu", "cuda", "auto", "meta"))

    import m4world_env  # noqa: F401 (registers M4World-v0)
    from m4world_env.policies import ConstantSpeedLaneKeeping

    kw = {"backend": "world_model", "checkpoint": str(tiny_bundle), "config": {"model": {"device": "meta"}}}
    kw["config"]["model"]["dtype"] = "float32"
    # Built outside the guard: modules are constructed on the host, then moved (load_world_model).
    # (Not a scenario with LoRA adapters: matching one fingerprints the weights, data meta has not.)
    env = gym.make("M4World-v0", scenario="merge_cut_in", **kw)
    venv = gym.make_vec("M4World-v0", num_envs=2, vectorization_mode="vector_entry_point", **kw)
    with OnDevice(META):
        env.reset(seed=0)
        for _ in range(2):
            env.step(ConstantSpeedLaneKeeping()(env.unwrapped.bridge))
        venv.reset(seed=0)
        obs, *_ = venv.step(venv.action_space.sample())
    assert env.unwrapped.backend.wm.student.patch_in.weight.device == META
    assert obs["cameras"].shape[0] == 2


def test_device_options_are_resolved_or_refused_by_name():
    from m4world_env.config import InvalidOptionError
    from m4world_env.env import M4WorldEnv
    from world_model.precision import resolve_device

    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="device must be auto, cpu, cuda or cuda:N, got 'gpu0'"):
        resolve_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(InvalidOptionError, match="config.model.device: device 'cuda:1' asked for, but this torch"):
            M4WorldEnv(backend="world_model", config={"model": {"device": "cuda:1"}})
