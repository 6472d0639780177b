"""How the causal student streams: :class:`StreamingConfig`, its bounds, and a bundle's ``streaming.json``.

One type with one meaning per value, wherever a streaming setting comes from: the bundle's file,
the env's config (``config={"model": {...}}``), the report's rows, ``m4world streaming`` and the
engine (``StudentConfig.streaming``). A source that sets only some settings passes those to
:meth:`StreamingConfig.override`; the others stay the base's (the bundle's file). Every value is
checked against one bounds table (:data:`STREAMING_BOUNDS`), and an error names the setting as its
source spells it (``config.model.sink_frames``, ``--sink-frames``, ``streaming.json: sink_frames``).
Training-only settings stay in :class:`~world_model.student.config.StudentConfig`.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

STREAMING_FILE = "streaming.json"
DIFFUSION_STEPS = 1000  # the scale the denoising steps are written on (1000 = pure noise)
REFRESH_EVERY_STEP = "all"  # refresh_steps: refresh the context frame at every denoising step (the paper's)
# Each denoising step is one forward pass of the student per chunk, beside the chunk's one cache
# write. 50 (12x the 4 the recipe's student stages distil at, 2.5x the teacher's 20-step sampler)
# keeps a step within seconds on a CPU; the schedule itself has DIFFUSION_STEPS levels, so more
# than that could not even be told apart.
MAX_DENOISING_STEPS = 50
# The KV cache holds sink + window frames of keys and values per rollout, allocated at its first
# commit (about 1 MB a frame for the shipped student in bf16), and every denoising pass attends to
# all of them: 64 sink frames is 16 times the shipped 4-frame window.
MAX_SINK_FRAMES = 64
# Classifier-free guidance extrapolates the prompt's direction by this factor; the model config's
# sampler guides at 3, and the bound refuses a digit's slip (30 for 3.0) rather than any scale in use.
MAX_GUIDANCE = 20.0
# What each setting allows, as every error message says it (n: the denoising steps).
STREAMING_BOUNDS = {
    "denoising_steps": f"an integer in [1, {MAX_DENOISING_STEPS}]",
    "context_refresh": "true or false",
    "refresh_steps": (
        f"{REFRESH_EVERY_STEP!r} or a non-empty list of denoising-step indices k with -n <= k < n "
        "(0: the first step, -1: the last)"
    ),
    "sink_frames": f"an integer in [0, {MAX_SINK_FRAMES}]",
    "first_frame_steps": f"an integer in [1, {MAX_DENOISING_STEPS}]",
    "first_frame_guidance": f"a number in [1, {MAX_GUIDANCE:g}] (1: no guidance)",
    "one_step_first_frame": "true or false",
}


SWITCH = "--[no-]"  # how a source names a true/false flag pair, e.g. "--[no-]refresh"


class StreamingConfigError(ValueError):
    """A streaming setting outside :data:`STREAMING_BOUNDS`: the message names the setting as its
    source spells it, the value, and what is allowed."""


@dataclass(frozen=True)
class StreamingConfig:
    """Inference settings of the causal student (the defaults are the shipped bundle's but for
    ``denoising_steps``, which a bundle's export writes as the steps its student was taught)."""

    denoising_steps: int = 4  # the student stages' count; evenly spaced from pure noise: 4 -> 1000, 750, 500, 250
    context_refresh: bool = True  # §4.2 latent context refresh of the previous chunk's last frame
    # With context_refresh: the denoising steps that refresh the context frame; the others attend
    # to the cache's copy. 0 = the first, -1 = the last; "all": every step (the paper's). The last
    # two scored like every step on the 4-step student for 12 frame passes a chunk instead of 14
    # (docs/experiments.md).
    refresh_steps: tuple[int, ...] | str = (-2, -1)
    # The first frames of a rollout kept in context beside the rolling window (an attention sink,
    # StreamingLLM / Deep Forcing); one frame lowers the shipped checkpoint's long-rollout errors.
    sink_frames: int = 1
    # The reference model's Euler steps for a rollout's first frame, most of a reset's time: the
    # shipped checkpoint's first frames are judged alike at 4 and at its sampler's 20
    # (docs/experiments.md).
    first_frame_steps: int = 4
    # The cameras' classifier-free guidance scale of that first frame. The model config's sampler
    # guides at 3; the shipped reference model then draws the light of dusk and night too dark
    # (the road in the ego's headlights most), and the student keeps that light for the episode
    # (docs/experiments.md).
    first_frame_guidance: float = 2.0
    # A first frame from controls alone in one unguided step of the bundle's first-frame model (when
    # the bundle has one: the reference model's sampler at the two settings above, distilled), not
    # in the reference model's first_frame_steps guided steps. The two settings above still set the
    # reference model's sampling: a first frame anchored on the user's images, an object completed.
    one_step_first_frame: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, check_setting(f.name, getattr(self, f.name)))
        check_refresh_within(self.refresh_steps, self.denoising_steps)

    def diffusion_steps(self) -> tuple[int, ...]:
        """The denoising steps on the 1000-step scale, from pure noise down."""
        n = self.denoising_steps
        return tuple(round(DIFFUSION_STEPS * (1 - k / n)) for k in range(n))

    def resolved_refresh_steps(self) -> tuple[int, ...]:
        """The denoising steps that refresh the context frame, as increasing indices from 0 (each
        once); none without ``context_refresh``."""
        if not self.context_refresh:
            return ()
        n = self.denoising_steps
        if self.refresh_steps == REFRESH_EVERY_STEP:
            return tuple(range(n))
        return tuple(sorted({k % n for k in self.refresh_steps}))

    def override(self, changes: Mapping[str, Any], names: Mapping[str, str] | None = None) -> StreamingConfig:
        """A copy with the settings of ``changes`` replaced (the others stay this config's), checked
        as :func:`check_changes` does and against this config: refresh steps given while this
        config's refresh is off are refused, and refresh steps left out are this config's, less
        those that name no step of a changed ``denoising_steps`` (the default ``[-2, -1]``, the last
        two steps, is ``[-1]`` with one step), refused when none is left."""
        name = _names(names)
        new = check_changes(changes, names)
        merged = asdict(self) | new
        if "refresh_steps" in new and not merged["context_refresh"]:
            raise StreamingConfigError(
                f"{_given(name['refresh_steps'], changes['refresh_steps'])} needs the context refresh, which the "
                f"bundle's streaming.json turns off: turn it on too ({_given(name['context_refresh'], True)})"
            )
        n, steps = merged["denoising_steps"], merged["refresh_steps"]
        if "refresh_steps" in new:
            check_refresh_within(steps, n, name["refresh_steps"])
        elif steps != REFRESH_EVERY_STEP:
            kept = tuple(k for k in steps if -n <= k < n)
            if not kept:
                raise StreamingConfigError(
                    f"{_given(name['denoising_steps'], n)} leaves none of the bundle's refresh_steps {list(steps)} "
                    f"naming a step; give {name['refresh_steps']} too: {STREAMING_BOUNDS['refresh_steps']}"
                )
            merged["refresh_steps"] = kept
        return StreamingConfig(**merged)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["refresh_steps"] != REFRESH_EVERY_STEP:
            d["refresh_steps"] = list(d["refresh_steps"])
        return d

    @classmethod
    def from_dict(cls, d: Any, source: str = STREAMING_FILE) -> StreamingConfig:
        """A config from its JSON form (keys left out: the defaults); refuses unknown keys and bad
        values, naming ``source`` and the key. A null ``refresh_steps`` reads as ``"all"`` (files
        that spell every step so)."""
        if not isinstance(d, dict):
            raise StreamingConfigError(f"{source} must hold a JSON object, got {type(d).__name__}")
        _refuse_unknown(d, source)
        if d.get("refresh_steps", ()) is None:
            d = {**d, "refresh_steps": REFRESH_EVERY_STEP}
        values = asdict(cls()) | {key: check_setting(key, value, f"{source}: {key}") for key, value in d.items()}
        check_refresh_within(values["refresh_steps"], values["denoising_steps"], f"{source}: refresh_steps")
        return cls(**values)


def taught_streaming(denoising_steps: int) -> StreamingConfig:
    """How a bundle streams a student taught ``denoising_steps`` unless it is told otherwise (the
    ``streaming.json`` that :func:`~world_model.bundle.export_bundle` writes): the defaults at those
    steps. The training stages that stream a run's student as the env would stream it use it too."""
    return StreamingConfig().override({"denoising_steps": denoising_steps})


def check_changes(changes: Mapping[str, Any], names: Mapping[str, str] | None = None) -> dict[str, Any]:
    """``changes`` to a streaming config in their one form (:func:`check_setting`), checked against
    each other as far as they go without the config they change: refresh steps within denoising steps
    given beside them, and no refresh steps beside ``context_refresh=False``. ``names`` spells each
    setting as the caller's source does (a config key, a CLI flag)."""
    name = _names(names)
    _refuse_unknown(changes, "streaming settings")
    new = {key: check_setting(key, value, name[key]) for key, value in changes.items()}
    if "refresh_steps" in new and new.get("context_refresh") is False:
        raise StreamingConfigError(
            f"{_given(name['refresh_steps'], changes['refresh_steps'])} needs the context refresh, which "
            f"{_given(name['context_refresh'], False)} turns off: leave one of them out"
        )
    if "refresh_steps" in new and "denoising_steps" in new:
        n = new["denoising_steps"]
        check_refresh_within(new["refresh_steps"], n, name["refresh_steps"], _given(name["denoising_steps"], n))
    return new


def check_setting(key: str, value: Any, name: str | None = None) -> Any:
    """``value`` of the streaming setting ``key`` in its one form (Python ints and bools, a tuple of
    refresh steps or ``"all"``; numpy scalars and 1-D integer arrays are taken as the numbers they
    hold), or :class:`StreamingConfigError` naming it ``name`` (default: ``key``) when it lies outside
    :data:`STREAMING_BOUNDS`. Refresh steps are only checked against the most steps allowed here:
    :func:`check_refresh_within` checks them against a config's own."""
    form = {
        "denoising_steps": _denoising_steps,
        "context_refresh": _bool,
        "refresh_steps": _refresh_steps,
        "first_frame_steps": _denoising_steps,
        "first_frame_guidance": _guidance,
        "one_step_first_frame": _bool,
    }
    checked = form.get(key, _sink_frames)(value)
    if checked is None:
        raise StreamingConfigError(f"{name or key} must be {STREAMING_BOUNDS[key]}, got {_shown(value)}")
    return checked


def check_refresh_within(steps: tuple[int, ...] | str, n: int, name: str = "refresh_steps", given: str = "") -> None:
    """Refuse refresh ``steps`` that name no step of ``n`` denoising steps (``given``: the denoising
    steps' setting as the caller's source spells it, when they were given beside the steps)."""
    if steps == REFRESH_EVERY_STEP:
        return
    outside = [k for k in steps if not -n <= k < n]
    if outside:
        given = f" ({given})" if given else ""
        raise StreamingConfigError(
            f"{_given(name, steps)} names no step of the {n} denoising steps{given} at {outside}: each index k "
            f"must have {-n} <= k < {n} (0: the first step, -1: the last), or give {REFRESH_EVERY_STEP!r}"
        )


def _names(names: Mapping[str, str] | None) -> dict[str, str]:
    """How each setting is spelled in messages: ``names``' spelling, else its key."""
    return {key: key for key in STREAMING_BOUNDS} | dict(names or {})


def _refuse_unknown(settings: Mapping[Any, Any], source: str) -> None:
    unknown = [key for key in settings if key not in STREAMING_BOUNDS]
    if unknown:
        raise StreamingConfigError(f"{source}: unknown keys {unknown}; allowed: {list(STREAMING_BOUNDS)}")


def _integer(value: Any) -> int | None:
    """``value`` as a Python int when it is an integer (numpy's included) other than a bool."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        return None
    return int(value)


def _in_range(value: Any, low: int, high: int) -> int | None:
    number = _integer(value)
    return number if number is not None and low <= number <= high else None


def _denoising_steps(value: Any) -> int | None:
    return _in_range(value, 1, MAX_DENOISING_STEPS)


def _sink_frames(value: Any) -> int | None:
    return _in_range(value, 0, MAX_SINK_FRAMES)


def _guidance(value: Any) -> float | None:
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        return None
    number = float(value)
    return number if 1.0 <= number <= MAX_GUIDANCE else None  # NaN fails both


def _bool(value: Any) -> bool | None:
    return bool(value) if isinstance(value, bool | np.bool_) else None


def _refresh_steps(value: Any) -> tuple[int, ...] | str | None:
    if isinstance(value, str) and value == REFRESH_EVERY_STEP:
        return REFRESH_EVERY_STEP
    if isinstance(value, np.ndarray) and value.ndim == 1:
        value = value.tolist()
    if not isinstance(value, list | tuple) or not value:  # a dict, set, string or bytes is no list of steps
        return None
    steps = tuple(_in_range(k, -MAX_DENOISING_STEPS, MAX_DENOISING_STEPS - 1) for k in value)
    return None if None in steps else steps


def _given(name: str, value: Any) -> str:
    """A setting and its value as its source spells them: ``key=value``, ``--flag value``, or a
    switch named ``--[no-]flag``: ``--flag`` for true, ``--no-flag`` for false."""
    if name.startswith(SWITCH):
        return "--" + "no-" * (not value) + name.removeprefix(SWITCH)
    return f"{name} {_shown(value)}" if name.startswith("--") else f"{name}={_shown(value)}"


def _shown(value: Any) -> str:
    """``value`` as an error message shows it: a short repr (a huge list or number is cut)."""
    text = repr(value.tolist() if isinstance(value, np.ndarray) else list(value) if isinstance(value, tuple) else value)
    return text if len(text) <= 80 else f"{text[:77]}..."
