"""Env configuration: one dataclass per concern, every default visible, unknown keys refused.

``gym.make("M4World-v0", config={...})`` takes a plain dict; :func:`EnvConfig.from_dict` turns
it into these dataclasses and names any key it does not know (with the closest valid one).
"""

from __future__ import annotations

import difflib
import math
import numbers
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from types import UnionType
from typing import Any, get_args, get_origin, get_type_hints

import numpy as np

from world_model.precision import DTYPES
from world_model.streaming import STREAMING_BOUNDS, StreamingConfigError, check_changes

ACTION_TYPES = ("continuous", "discrete_meta")
OBSERVATION_KEYS = ("cameras", "lidar", "bev", "state")
BACKENDS = ("procedural", "world_model")
# Bounds that keep every call finite in time and memory and every reward finite.
MAX_REWARD_WEIGHT = 1.0e3
MAX_SPEED_RANGE_MPS = 100.0
MAX_STATE_OBJECTS = 256
MIN_VIEW_PX, MAX_VIEW_PX = 16, 1024  # the procedural rig's height and width
DEVICE_TYPES = ("cpu", "cuda", "auto")
MAX_TORCH_THREADS = 256
DEFAULT_TORCH_THREADS = 1  # ModelBackendConfig.threads
MAX_WORKERS = 256  # EnvConfig.workers: simulation worker processes of a vector env


class UnknownOptionError(KeyError):
    """A config/option key the env does not know. The message names it and suggests the closest."""

    def __str__(self) -> str:  # KeyError quotes its message; show it plainly
        return str(self.args[0])


class InvalidOptionError(ValueError):
    """A known option with a value the env cannot use."""


@dataclass
class RewardConfig:
    """highway-env style reward terms and weights (see :mod:`m4world_env.rewards`)."""

    collision: float = -1.0
    high_speed: float = 0.4
    right_lane: float = 0.1
    on_road: float = 0.0
    progress: float = 0.0
    speed_range: tuple[float, float] = (20.0, 30.0)  # m/s mapped to high_speed term 0..1
    normalize: bool = True  # map the weighted sum to [0, 1] like highway-env
    on_road_gate: bool = True  # multiply the reward by on_road (highway-env does)


@dataclass
class ModelBackendConfig:
    """Options of the world-model backend (ignored by the procedural one)."""

    # Streaming (world_model.streaming.StreamingConfig: its fields, bounds and meanings):
    # None takes the bundle's streaming.json (the shipped one: 4 denoising steps, context refresh
    # at the last two, one sink frame, 4 first-frame steps guided at 2); a value replaces it. refresh_steps:
    # the denoising-step indices that refresh the context frame (0 = the first, -1 = the last) or
    # "all"; sink_frames: the first frames of an episode kept in context beside the rolling window;
    # first_frame_steps: the reference model's Euler steps for an episode's first frame (a reset);
    # first_frame_guidance: the cameras' classifier-free guidance scale of that frame (1: none);
    # one_step_first_frame: a first frame from controls in one step of the bundle's first-frame model,
    # when it has one (False: the reference model's first_frame_steps guided steps).
    denoising_steps: int | None = None
    context_refresh: bool | None = None
    refresh_steps: tuple[int, ...] | str | None = None
    sink_frames: int | None = None
    first_frame_steps: int | None = None
    first_frame_guidance: float | None = None
    one_step_first_frame: bool | None = None
    # Where the model runs: "cpu", "cuda", "cuda:N", or "auto" (CUDA when torch sees it, else CPU).
    device: str = "cpu"
    # DiT weights and activations (and the camera decoder): "auto" = bf16 where the checkpoint was
    # trained for it (the default preset) and the device multiplies bf16 faster than float32 (bf16
    # GPUs, AMX CPUs, AVX512-BF16 but Intel's: world_model/precision.py), else float32; or force
    # "float32" / "bfloat16". LiDAR decodes in float32.
    dtype: str = "auto"
    # torch.compile the student's blocks (see MultiViewDiT.compile_blocks): faster steps after
    # a one-off compilation of tens of seconds at the first steps; needs a C++ compiler.
    compile: bool = False
    # torch intra-op threads of the process (torch.set_num_threads, process-wide): one thread keeps
    # a step from collapsing when other processes (other envs, a learner) share the cores
    # (docs/performance.md, m4world bench threads). None leaves torch's setting as it is.
    threads: int | None = DEFAULT_TORCH_THREADS
    # A vector env's rollouts stepped in this many groups at once, a Python thread each
    # (world_model.rollout.shards): None = as many as the process's CPUs hold groups of ``threads``
    # torch threads (on CPU; one on a GPU), at most one a sub-env; a single env then decodes on a
    # second thread beside the student's cache writes (a step's, a reset's). The observations are
    # the same bit for bit whatever the number (docs/performance.md).
    rollout_threads: int | None = None

    def streaming_changes(self) -> dict[str, Any]:
        """The streaming settings given (not None): changes to the bundle's streaming.json."""
        return {key: getattr(self, key) for key in STREAMING_BOUNDS if getattr(self, key) is not None}


# How the env's config spells each streaming setting in error messages.
STREAMING_NAMES = {key: f"config.model.{key}" for key in STREAMING_BOUNDS}


@dataclass
class EnvConfig:
    action_type: str = "continuous"
    observation_keys: tuple[str, ...] = ("cameras", "lidar")
    # Rig resolution for the procedural backend; the world-model backend uses its checkpoint's.
    height: int = 64
    width: int = 112
    state_objects: int = 8  # nearest objects in the "state" observation
    offroad_terminal: bool = True
    reward: RewardConfig = field(default_factory=RewardConfig)
    model: ModelBackendConfig = field(default_factory=ModelBackendConfig)
    # Vector env, world-model backend: worker processes that run the sub-envs' traffic, reference
    # crops and condition arrays beside the batched model (m4world_env.workers, docs/scaling.md);
    # 0 runs them in the vector env's process.
    workers: int = 0

    def __post_init__(self) -> None:
        if self.action_type not in ACTION_TYPES:
            raise InvalidOptionError(f"config.action_type must be one of {ACTION_TYPES}, got {self.action_type!r}")
        self.observation_keys = _observation_keys(self.observation_keys)
        for name in ("height", "width"):
            _check_int_range(getattr(self, name), MIN_VIEW_PX, MAX_VIEW_PX, f"config.{name}")
        _check_int_range(self.state_objects, 1, MAX_STATE_OBJECTS, "config.state_objects")
        _check_int_range(self.workers, 0, MAX_WORKERS, "config.workers")
        r = self.reward
        for name in ("collision", "high_speed", "right_lane", "on_road", "progress"):
            if abs(getattr(r, name)) > MAX_REWARD_WEIGHT:
                raise InvalidOptionError(
                    f"config.reward.{name} must lie in [-{MAX_REWARD_WEIGHT:g}, {MAX_REWARD_WEIGHT:g}], "
                    f"got {getattr(r, name)!r}"
                )
        pair = _number_tuple(r.speed_range)
        if pair is None or len(pair) != 2 or not 0 <= pair[0] < pair[1] <= MAX_SPEED_RANGE_MPS:
            raise InvalidOptionError(
                f"config.reward.speed_range must be (low, high) m/s with 0 <= low < high <= {MAX_SPEED_RANGE_MPS:g}, "
                f"got {r.speed_range!r}"
            )
        m = self.model
        try:
            for key, value in check_changes(m.streaming_changes(), STREAMING_NAMES).items():
                setattr(m, key, value)
        except StreamingConfigError as e:
            raise InvalidOptionError(str(e)) from e
        if m.threads is not None:
            _check_int_range(m.threads, 1, MAX_TORCH_THREADS, "config.model.threads")
        if m.rollout_threads is not None:
            _check_int_range(m.rollout_threads, 1, MAX_TORCH_THREADS, "config.model.rollout_threads")
            if m.compile and m.rollout_threads > 1:
                raise InvalidOptionError(
                    f"config.model.rollout_threads={m.rollout_threads} needs config.model.compile off: compiled "
                    "blocks step the rollouts on one thread"
                )
        device = m.device.split(":", 1)
        if device[0] not in DEVICE_TYPES or (len(device) == 2 and (device[0] != "cuda" or not device[1].isdigit())):
            raise InvalidOptionError(f"config.model.device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {m.device!r}")
        if self.model.dtype not in DTYPES:
            raise InvalidOptionError(f"config.model.dtype must be one of {DTYPES}, got {self.model.dtype!r}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> EnvConfig:
        return _build(cls, {} if d is None else d, "config")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _observation_keys(keys: Any) -> tuple[str, ...]:
    """``config.observation_keys`` as a tuple of distinct names from :data:`OBSERVATION_KEYS`: given
    as a list or tuple, or as a set (taken in :data:`OBSERVATION_KEYS` order, the same in every
    process). A string or a dict is refused rather than read as its characters or keys."""
    wanted = f"a non-empty list of distinct keys from {OBSERVATION_KEYS}"
    if not isinstance(keys, list | tuple | set | frozenset | np.ndarray):
        raise InvalidOptionError(f"config.observation_keys must be {wanted}, got {keys!r}")
    items = keys.tolist() if isinstance(keys, np.ndarray) else list(keys)
    bad = [k for k in items if not isinstance(k, str) or k not in OBSERVATION_KEYS]
    if bad or not items:
        raise InvalidOptionError(f"config.observation_keys must be {wanted}, got {keys!r}")
    repeated = sorted({k for k in items if items.count(k) > 1})
    if repeated:
        raise InvalidOptionError(f"config.observation_keys must be {wanted}, got {keys!r} ({repeated} repeated)")
    if isinstance(keys, set | frozenset):
        return tuple(k for k in OBSERVATION_KEYS if k in keys)
    return tuple(items)


def _check_int_range(value: Any, low: int, high: int, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value <= high:
        raise InvalidOptionError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


def _number_tuple(x: Any, kind: type = numbers.Real) -> tuple[Any, ...] | None:
    """``x`` as a tuple of finite numbers of ``kind``, or None when it is not one (bools refused)."""
    try:
        items = tuple(x)
    except TypeError:
        return None
    ok = all(isinstance(k, kind) and not isinstance(k, bool) and math.isfinite(k) for k in items)
    return items if ok else None


def _build(cls: type, d: dict[str, Any], path: str) -> Any:
    if not isinstance(d, dict):
        raise InvalidOptionError(f"{path} must be a dict, got {type(d).__name__}")
    known = {f.name: f for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in d.items():
        if not isinstance(key, str):
            raise UnknownOptionError(
                f"option names in {path} must be strings, got {key!r}; valid keys: {sorted(known)}"
            )
        if key not in known:
            close = difflib.get_close_matches(key, list(known), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise UnknownOptionError(f"unknown option {path}.{key}{hint}; valid keys: {sorted(known)}")
        factory = known[key].default_factory
        nested_cls = factory if isinstance(factory, type) and is_dataclass(factory) else None
        kwargs[key] = _build(nested_cls, value, f"{path}.{key}") if nested_cls else value
    hints = get_type_hints(cls)
    for key, value in kwargs.items():
        _check_type(value, hints[key], f"{path}.{key}")
    try:
        return cls(**kwargs)
    except TypeError as e:
        raise InvalidOptionError(f"{path}: {e}") from e


def _check_type(value: Any, kind: Any, name: str) -> None:
    """Refuse a value of the wrong type for a scalar option (a bool given as "no" would otherwise
    count as True, a weight given as a string fail only at the first step); float options must be
    finite. Options of other types (tuples, nested configs) are checked where they are used."""
    if get_origin(kind) is UnionType and type(None) in get_args(kind):  # an optional setting
        if value is None:
            return
        kind = next(k for k in get_args(kind) if k is not type(None))
    is_bool = isinstance(value, bool | np.bool_)
    if kind is bool and not is_bool:
        raise InvalidOptionError(f"{name} must be True or False, got {value!r}")
    if kind is int and (is_bool or not isinstance(value, numbers.Integral)):
        raise InvalidOptionError(f"{name} must be an integer, got {value!r}")
    if kind is float and (is_bool or not isinstance(value, numbers.Real) or not math.isfinite(value)):
        raise InvalidOptionError(f"{name} must be a finite number, got {value!r}")
    if kind is str and not isinstance(value, str):
        raise InvalidOptionError(f"{name} must be a string, got {value!r}")
    if kind == tuple[float, float]:
        pair = _number_tuple(value)
        if pair is None or len(pair) != 2:
            raise InvalidOptionError(f"{name} must be two finite numbers (low, high), got {value!r}")
