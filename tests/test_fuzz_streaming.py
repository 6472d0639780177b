"""Property-based fuzzing of the streaming settings through their three doors: the env's config
(``config={"model": {...}}``), a bundle's ``streaming.json`` and ``m4world streaming --write``. Every
input is either refused by the project's error naming the setting as that door spells it, or gives
a streaming config inside the bounds table, whose refresh steps each name a denoising step and
which survives its JSON form.

Derandomized like ``tests/test_fuzz.py`` (``tests/fuzz_settings.py``); ``FUZZ_EXAMPLES`` scales the
number of cases.
"""

import json
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from m4world_env.cli import main
from m4world_env.config import STREAMING_NAMES, EnvConfig, InvalidOptionError, UnknownOptionError
from tests.fuzz_settings import EXAMPLES, FUZZ
from world_model.bundle import STREAMING_FILE
from world_model.streaming import (
    MAX_DENOISING_STEPS,
    MAX_GUIDANCE,
    MAX_SINK_FRAMES,
    REFRESH_EVERY_STEP,
    STREAMING_BOUNDS,
    StreamingConfig,
    StreamingConfigError,
)

# Each CLI case reads and re-seals a bundle (~0.1 s): a quarter of the cases keeps the file quick.
CLI_FUZZ = settings(FUZZ, max_examples=max(1, EXAMPLES // 4))

# Integers around every bound, and far past them.
NUMBERS = st.one_of(
    st.integers(-MAX_DENOISING_STEPS - 2, MAX_SINK_FRAMES + 2),
    st.sampled_from([10**6, 10**30, -(2**63), 2**64]),
)
# What a user may pass for a streaming setting: the numbers as Python and numpy values, flags,
# lists and arrays of steps, and the wrong types.
VALUES = st.one_of(
    st.none(),
    NUMBERS,
    st.integers(-MAX_DENOISING_STEPS - 2, MAX_SINK_FRAMES + 2).map(np.int64),
    st.booleans(),
    st.sampled_from(
        [np.True_, np.False_, REFRESH_EVERY_STEP, "0", b"\x00", 2.0, 0.99, 20.5, float("inf"), float("nan")]
    ),
    st.lists(NUMBERS, max_size=3),
    st.lists(st.integers(-6, 6), min_size=1, max_size=3).map(np.array),
    st.dictionaries(st.integers(0, 3), st.integers(0, 3), max_size=2),
)
SETTINGS = st.dictionaries(st.sampled_from(list(STREAMING_BOUNDS)), VALUES, max_size=4)


def assert_inside_bounds(config: StreamingConfig) -> None:
    n = config.denoising_steps
    assert type(n) is int and 1 <= n <= MAX_DENOISING_STEPS
    assert type(config.sink_frames) is int and 0 <= config.sink_frames <= MAX_SINK_FRAMES
    assert type(config.context_refresh) is bool
    assert type(config.first_frame_guidance) is float and 1.0 <= config.first_frame_guidance <= MAX_GUIDANCE
    if config.refresh_steps != REFRESH_EVERY_STEP:
        assert config.refresh_steps and all(type(k) is int and -n <= k < n for k in config.refresh_steps)
    assert all(0 <= k < n for k in config.resolved_refresh_steps())
    assert StreamingConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


@FUZZ
@given(SETTINGS)
def test_env_config_streaming_is_refused_by_name_or_inside_the_bounds(model):
    """The env's config, then the bundle's settings changed by it (as the world-model backend does)."""
    try:
        changes = EnvConfig.from_dict({"model": model}).model.streaming_changes()
        config = StreamingConfig().override(changes, STREAMING_NAMES)
    except (InvalidOptionError, UnknownOptionError, StreamingConfigError) as e:
        assert any(f"config.model.{key}" in str(e) for key in model), e
        return
    assert_inside_bounds(config)
    given_steps = model.get("refresh_steps")
    if given_steps is not None and config.refresh_steps != REFRESH_EVERY_STEP:
        assert config.refresh_steps == tuple(int(k) for k in given_steps)  # taken as given, never clamped


@FUZZ
@given(SETTINGS)
def test_streaming_file_is_refused_by_name_or_inside_the_bounds(content):
    try:
        config = StreamingConfig.from_dict(content, "bundle/streaming.json")
    except StreamingConfigError as e:
        assert any(f"bundle/streaming.json: {key}" in str(e) for key in content), e
        return
    assert_inside_bounds(config)


CLI_FLAGS = st.fixed_dictionaries(
    {},
    optional={
        "--denoising-steps": NUMBERS.map(str),
        "--sink-frames": NUMBERS.map(str),
        "--refresh-steps": st.one_of(
            st.just(REFRESH_EVERY_STEP), st.lists(NUMBERS, min_size=1, max_size=3).map(lambda k: ",".join(map(str, k)))
        ),
        "--first-frame-guidance": st.one_of(NUMBERS.map(str), st.sampled_from(["1.5", "0.5", "nan", "inf"])),
        "--no-refresh": st.just(None),
        "--refresh": st.just(None),
    },
)


@pytest.fixture(scope="module")
def bundle(tiny_bundle, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz_streaming") / "bundle"
    shutil.copytree(tiny_bundle, root)
    return root


@CLI_FUZZ
@given(CLI_FLAGS)
def test_cli_writes_only_streaming_inside_the_bounds(bundle, capsys, flags):
    if "--refresh" in flags and "--no-refresh" in flags:
        flags.pop("--refresh")  # argparse takes the last of the pair: one is enough
    args = [flag if value is None else f"{flag}={value}" for flag, value in flags.items()]
    before = (bundle / STREAMING_FILE).read_text()
    code = main(["streaming", "--checkpoint", str(bundle), *args, "--write"])
    if code != 0:
        error = capsys.readouterr().err
        assert any(flag in error for flag in flags), error
        assert (bundle / STREAMING_FILE).read_text() == before  # nothing written
        return
    capsys.readouterr()
    assert_inside_bounds(StreamingConfig.from_dict(json.loads((bundle / STREAMING_FILE).read_text())))
