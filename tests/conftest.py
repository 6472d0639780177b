"""Test-session settings shared by every test module."""

import os

import torch

# pytest-xdist runs one worker per core: one intra-op thread each avoids oversubscribing the CPU.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_bundle(tmp_path_factory):
    """An untrained tiny-preset checkpoint bundle (VAE + student + reference model): enough to
    exercise the world-model backend's plumbing, shapes, seeding and errors."""
    from world_model.runtime import save_untrained_bundle

    return save_untrained_bundle(tmp_path_factory.mktemp("bundle") / "tiny")
