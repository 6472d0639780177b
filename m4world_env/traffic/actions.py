"""Ego actions, mapped exactly like highway-env's ``ContinuousAction`` and ``DiscreteMetaAction``."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from numbers import Integral

import numpy as np

ACTION_TYPES = ("continuous", "discrete_meta")
META_ACTIONS = {0: "LANE_LEFT", 1: "IDLE", 2: "LANE_RIGHT", 3: "FASTER", 4: "SLOWER"}
META_INDEX = {v: k for k, v in META_ACTIONS.items()}


class ActionError(ValueError):
    """An ego action has the wrong type, shape, value or range."""


@dataclass(frozen=True)
class ActionConfig:
    """ContinuousAction ranges are highway-env's. Meta-action target speeds are MDPVehicle's
    mechanism with a wider grid: ``linspace(0, 1, 5) * speed_limit`` (0, 7.5, ..., 30 m/s for a
    30 m/s limit) instead of highway-env's fixed (20, 25, 30), so that a meta-action ego can
    stop for pedestrians and queues and slow down on 12 m/s junction roads."""

    acceleration_range: tuple[float, float] = (-5.0, 5.0)  # m/s^2 for action[0] = -1 .. +1
    steering_range: tuple[float, float] = (-math.pi / 4, math.pi / 4)  # rad for action[1] = -1 .. +1
    target_speed_fractions: tuple[float, float] = (0.0, 1.0)  # of the ego lane's speed limit
    target_speed_count: int = 5

    def target_speeds(self, speed_limit: float) -> np.ndarray:
        lo, hi = self.target_speed_fractions
        return np.linspace(lo * speed_limit, hi * speed_limit, self.target_speed_count)


def detached(action: object) -> object:
    """``action`` with a torch tensor in it (the action itself, or items of its list or tuple) as a
    CPU numpy array, out of any autograd graph: a policy's output is an action as it comes, on any
    device. Everything else is returned as it is."""
    torch = sys.modules.get("torch")  # no tensor exists before torch is imported: nothing to convert
    if torch is None:
        return action
    if isinstance(action, torch.Tensor):
        tensor = action.detach()
        # numpy has no bfloat16; float32 holds every bfloat16 value exactly.
        return (tensor.float() if tensor.dtype == torch.bfloat16 else tensor).numpy(force=True)
    if isinstance(action, list | tuple) and any(isinstance(a, torch.Tensor) for a in action):
        return [detached(a) for a in action]
    return action


def _lmap(v: float, rng: tuple[float, float]) -> float:
    """highway-env's utils.lmap from [-1, 1] to ``rng``."""
    return rng[0] + (v + 1.0) * (rng[1] - rng[0]) / 2.0


def continuous_controls(action: object, cfg: ActionConfig) -> dict[str, float]:
    """[acceleration, steering] in [-1, 1]^2 -> highway-env controls, exactly as highway-env's
    ContinuousAction: steering +1 is +pi/4 in highway-env's clockwise convention, i.e. a turn to
    the RIGHT (policies trained on highway-env keep their meaning). ``EgoState.steering`` reports
    the same angle in our counter-clockwise convention (negated). Raises :class:`ActionError`."""
    try:
        raw = np.asarray(detached(action))
    except (TypeError, ValueError, OverflowError) as err:
        raise ActionError(f"continuous action must be numeric [acceleration, steering], got {action!r}") from err
    # Only real numbers: strings, booleans, complex numbers, dates (and ints too large for any dtype,
    # which numpy keeps as objects) would otherwise be coerced into some float.
    if raw.dtype.kind not in "iuf":
        raise ActionError(
            f"continuous action must be numeric: two real numbers [acceleration, steering], got {action!r} "
            f"(dtype {raw.dtype})"
        )
    a = raw.astype(np.float64)
    if a.shape != (2,):
        raise ActionError(f"continuous action must have shape (2,) [acceleration, steering], got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ActionError(f"continuous action contains NaN or inf: {a.tolist()}")
    if np.any(np.abs(a) > 1.0):
        raise ActionError(f"continuous action must lie in [-1, 1]^2, got {a.tolist()}")
    return {
        "acceleration": _lmap(float(a[0]), cfg.acceleration_range),
        "steering": _lmap(float(a[1]), cfg.steering_range),
    }


def meta_action(action: object) -> str:
    """0..4 -> "LANE_LEFT" .. "SLOWER". Raises :class:`ActionError` on bad input."""
    action = detached(action)
    if isinstance(action, np.ndarray) and action.size == 1 and np.issubdtype(action.dtype, np.integer):
        action = action.reshape(()).item()
    if isinstance(action, bool) or not isinstance(action, Integral):
        raise ActionError(f"discrete_meta action must be an integer in 0..4 {META_ACTIONS}, got {action!r}")
    if int(action) not in META_ACTIONS:
        raise ActionError(f"discrete_meta action must be in 0..4 {META_ACTIONS}, got {int(action)}")
    return META_ACTIONS[int(action)]
