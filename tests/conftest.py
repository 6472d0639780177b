"""Test-session settings shared by every test module."""

import os

import torch

# pytest-xdist runs one worker per core: one intra-op thread each avoids oversubscribing the CPU.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


import pytest  # noqa: E402


@pytest.fixture(scope="session", autouse=True)
def _sb3_logs_in_test_tmp(tmp_path_factory):
    """Stable-Baselines3 makes a log folder per ``learn`` call, in the system's temp folder unless
    ``SB3_LOGDIR`` names one: keep them with the session's other temporary files."""
    os.environ.setdefault("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3_logs")))


@pytest.fixture(scope="session")
def tiny_bundle(tmp_path_factory):
    """An untrained tiny-preset checkpoint bundle (VAE + student + reference model): enough to
    exercise the world-model backend's plumbing, shapes, seeding and errors."""
    from world_model.rollout.runtime import save_untrained_bundle

    return save_untrained_bundle(tmp_path_factory.mktemp("bundle") / "tiny")


@pytest.fixture(scope="session")
def layout_bundle(tmp_path_factory):
    """An untrained tiny bundle with pixel-aligned layout conditioning: the DiT's layout channels
    and a decoder that draws each camera's label maps, their paint and the scene's style."""
    from world_model.rollout.runtime import save_untrained_bundle

    return save_untrained_bundle(tmp_path_factory.mktemp("bundle") / "tiny_layout", layout=True)


@pytest.fixture(scope="session")
def active_bundle(tiny_bundle, tmp_path_factory):
    """``tiny_bundle`` with noise on the student's and reference model's weights: an untrained DiT's
    zero-initialized output ignores its controls and context (adaLN-zero), so only a bundle like
    this one shows a test that actions, scenarios and batch rows actually reach the model."""
    import torch

    from world_model.bundle import load_bundle_files, save_bundle

    files = load_bundle_files(tiny_bundle)
    gen = torch.Generator().manual_seed(0)
    tensors = dict(files.tensors)
    for part in ("student", "reference"):
        tensors[part] = {k: v + 0.05 * torch.randn(v.shape, generator=gen) for k, v in tensors[part].items()}
    configs = {"reference": files.component_config("reference")}
    return save_bundle(
        tmp_path_factory.mktemp("bundle") / "active", files.model_config, tensors, component_configs=configs
    )


@pytest.fixture(scope="session")
def first_frame_bundle(active_bundle, tmp_path_factory):
    """``active_bundle`` with a one-step first-frame model: the reference model's weights with
    other noise on them (a first frame it draws differs from the reference model's)."""
    import torch

    from world_model.bundle import load_bundle_files, save_bundle

    files = load_bundle_files(active_bundle)
    gen = torch.Generator().manual_seed(1)
    tensors = dict(files.tensors)
    noisy = {k: v + 0.05 * torch.randn(v.shape, generator=gen) for k, v in tensors["reference"].items()}
    tensors["first_frame"] = noisy
    own = files.component_config("reference")
    return save_bundle(
        tmp_path_factory.mktemp("bundle") / "first_frame",
        files.model_config,
        tensors,
        component_configs={"reference": own, "first_frame": own},
    )


@pytest.fixture(scope="session")
def range_head_bundle(layout_bundle, tmp_path_factory):
    """``layout_bundle`` whose VAE finishes the LiDAR with a range head (``layout.range_head``), its
    last layer's weights random so that the head moves the LiDAR (a zero-initialized one does not)."""
    import copy

    import torch

    from world_model.bundle import load_bundle_files, save_bundle
    from world_model.model.config import ModelConfig
    from world_model.model.vae import SensorVAE
    from world_model.train.range_head_stage import with_range_head

    files = load_bundle_files(layout_bundle)
    cfg = with_range_head(ModelConfig.from_dict(files.model_config))
    vae = SensorVAE(cfg)
    vae.load_state_dict(files.tensors["vae"], strict=False)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        vae.range_head.net[-1].weight.copy_(0.2 * torch.randn(vae.range_head.net[-1].weight.shape, generator=gen))
        vae.range_head.net[-1].bias.fill_(0.5)
    tensors = {**copy.copy(files.tensors), "vae": vae.state_dict()}
    configs = {"reference": files.component_config("reference")}
    return save_bundle(
        tmp_path_factory.mktemp("bundle") / "range_head", cfg.to_dict(), tensors, component_configs=configs
    )
