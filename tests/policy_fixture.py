"""A user policy for the harness tests: brake gently, keep the wheel straight."""

import numpy as np


def brake(obs, info):
    return np.array([-0.2, 0.0], dtype=np.float32)


def make_braker(e):
    """A policy factory: takes the env (any parameter name), returns the policy."""
    assert hasattr(e, "action_space")
    return brake
