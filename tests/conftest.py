"""Test-session settings shared by every test module."""

import os

import torch

# pytest-xdist runs one worker per core: one intra-op thread each avoids oversubscribing the CPU.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
