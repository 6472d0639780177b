"""Streaming settings: one type (StreamingConfig) and one bounds table for the bundle's streaming.json,
the env's config, the report's rows, ``m4world streaming`` and the engine."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from m4world_env.cli import main
from m4world_env.config import EnvConfig, InvalidOptionError
from m4world_env.env import M4WorldEnv
from m4world_env.vector import M4WorldVectorEnv
from world_model.bundle import STREAMING_FILE, CheckpointError, load_bundle_files, reseal_bundle, set_streaming
from world_model.eval.report import StudentStreaming
from world_model.rollout.runtime import load_world_model
from world_model.streaming import REFRESH_EVERY_STEP, StreamingConfig, StreamingConfigError
from world_model.student.config import TRAINING_STREAMING, StudentConfig


@pytest.fixture
def bundle(tiny_bundle, tmp_path):
    """A copy of the tiny bundle that a test may rewrite."""
    root = tmp_path / "bundle"
    shutil.copytree(tiny_bundle, root)
    return root


def test_defaults_are_what_the_env_runs_and_training_rolls_out_its_own():
    s = StreamingConfig()
    assert s.diffusion_steps() == (1000, 750, 500, 250)
    assert s.resolved_refresh_steps() == (2, 3) and s.sink_frames == 1
    # The student stages roll out refreshing at every step, without a sink: a named config of the same type.
    assert StudentConfig().streaming == TRAINING_STREAMING
    assert TRAINING_STREAMING.resolved_refresh_steps() == (0, 1, 2, 3) and TRAINING_STREAMING.sink_frames == 0


def test_refresh_steps_resolve_against_the_denoising_steps():
    def resolved(**changes) -> tuple[int, ...]:
        return StreamingConfig().override(changes).resolved_refresh_steps()

    assert resolved(denoising_steps=6) == (4, 5)
    assert resolved(denoising_steps=1) == (0,)  # of the last two, only the last names a step of one
    assert resolved(refresh_steps=[3, -4, 0]) == (0, 3)  # -4 of 4 is step 0: each step once, in order
    assert resolved(refresh_steps=REFRESH_EVERY_STEP) == (0, 1, 2, 3)
    assert resolved(context_refresh=False) == ()
    with pytest.raises(
        StreamingConfigError, match=r"denoising_steps=1 leaves none of the bundle's refresh_steps \[2\]"
    ):
        StreamingConfig(refresh_steps=(2,)).override({"denoising_steps": 1})


def test_none_is_never_a_streaming_value():
    """None means "not given" (the bundle's) in the env's config and the report, so it is no
    streaming value: every step is "all"."""
    with pytest.raises(StreamingConfigError, match="refresh_steps must be 'all' or a non-empty list"):
        StreamingConfig(refresh_steps=None)
    env = EnvConfig.from_dict({"model": {"refresh_steps": "all", "sink_frames": 0}}).model
    from_env = StreamingConfig().override(env.streaming_changes())
    from_report = StudentStreaming(refresh_steps="all", sink_frames=0).streaming(StreamingConfig())
    assert from_env == from_report == StreamingConfig(refresh_steps="all", sink_frames=0)


# Out of bounds, as each source can say it: (settings, the setting named, the value shown).
OUT_OF_BOUNDS = [
    ({"denoising_steps": 0}, "denoising_steps", "0"),
    ({"denoising_steps": 51}, "denoising_steps", "51"),
    ({"denoising_steps": 10**30}, "denoising_steps", str(10**30)),
    ({"sink_frames": -1}, "sink_frames", "-1"),
    ({"sink_frames": 65}, "sink_frames", "65"),
    ({"sink_frames": 1_000_000}, "sink_frames", "1000000"),
    ({"refresh_steps": [4]}, "refresh_steps", "[4]"),  # the bundle's 4 steps are -4 .. 3
    ({"refresh_steps": [-5]}, "refresh_steps", "[-5]"),
    ({"refresh_steps": [-(2**63)]}, "refresh_steps", str(-(2**63))),
    ({"denoising_steps": 2, "refresh_steps": [-3]}, "refresh_steps", "[-3]"),
    ({"refresh_steps": {0: 1}}, "refresh_steps", "{0: 1}"),
    ({"refresh_steps": b"\x00"}, "refresh_steps", r"b'\x00'"),
    ({"refresh_steps": []}, "refresh_steps", "[]"),
    ({"first_frame_steps": 0}, "first_frame_steps", "0"),
    ({"first_frame_steps": 51}, "first_frame_steps", "51"),
    ({"first_frame_guidance": 0.5}, "first_frame_guidance", "0.5"),
    ({"first_frame_guidance": 21}, "first_frame_guidance", "21"),
    ({"first_frame_guidance": float("nan")}, "first_frame_guidance", "nan"),
]
CLI_FLAGS = {
    "denoising_steps": "--denoising-steps",
    "sink_frames": "--sink-frames",
    "refresh_steps": "--refresh-steps",
    "first_frame_steps": "--first-frame-steps",
    "first_frame_guidance": "--first-frame-guidance",
}


def _cli_args(settings: dict) -> list[str] | None:
    """``settings`` as m4world streaming's flags; None when a flag cannot say them."""
    args = []
    for key, value in settings.items():
        if isinstance(value, dict | bytes) or value == []:
            return None
        args += [CLI_FLAGS[key], ",".join(map(str, value)) if isinstance(value, list) else str(value)]
    return args


@pytest.mark.parametrize(("settings", "key", "shown"), OUT_OF_BOUNDS)
def test_one_bounds_table_for_the_env_the_cli_and_the_bundles_file(bundle, capsys, settings, key, shown):
    with pytest.raises(InvalidOptionError) as refused:
        M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(bundle), config={"model": settings})
    assert f"config.model.{key}" in str(refused.value) and shown in str(refused.value)
    assert "must" in str(refused.value)  # and says what is allowed

    with pytest.raises(StreamingConfigError) as refused:
        StreamingConfig.from_dict(settings, "my.json")
    assert f"my.json: {key}" in str(refused.value) and shown in str(refused.value)

    args = _cli_args(settings)
    if args is not None:
        before = (bundle / STREAMING_FILE).read_text()
        assert main(["streaming", "--checkpoint", str(bundle), *args, "--write"]) == 2
        error = capsys.readouterr().err
        assert CLI_FLAGS[key] in error and shown in error and "must" in error, error
        assert (bundle / STREAMING_FILE).read_text() == before  # nothing written


def test_refresh_steps_need_the_refresh_in_the_env_the_cli_and_the_report(bundle, capsys):
    both = {"context_refresh": False, "refresh_steps": [0]}
    with pytest.raises(InvalidOptionError, match=r"config.model.refresh_steps=\[0\] needs the context refresh"):
        EnvConfig.from_dict({"model": both})
    assert main(["streaming", "--checkpoint", str(bundle), "--no-refresh", "--refresh-steps", "0", "--write"]) == 2
    assert "--refresh-steps [0] needs the context refresh, which --no-refresh turns off" in capsys.readouterr().err
    # A bundle streaming without refresh: refresh steps alone are refused, with the refresh they are taken.
    assert main(["streaming", "--checkpoint", str(bundle), "--no-refresh", "--write"]) == 0
    assert main(["streaming", "--checkpoint", str(bundle), "--refresh-steps", "0"]) == 2
    assert "turn it on too (--refresh)" in capsys.readouterr().err
    with pytest.raises(InvalidOptionError, match=r"turn it on too \(config.model.context_refresh=True\)"):
        M4WorldEnv(
            "highway_sunny_day", backend="world_model", checkpoint=str(bundle), config={"model": {"refresh_steps": [0]}}
        )
    assert main(["streaming", "--checkpoint", str(bundle), "--refresh", "--refresh-steps", "0", "--write"]) == 0
    assert load_world_model(str(bundle)).streaming == StreamingConfig(refresh_steps=(0,))
    # The report's refresh rows turn the refresh on themselves: they are asked for by their steps.
    row = StudentStreaming(refresh_steps=(1,)).streaming(replace(StreamingConfig(), context_refresh=False))
    assert row.resolved_refresh_steps() == (1,)


def test_numpy_numbers_are_taken_as_the_numbers_they_hold(tiny_bundle):
    given = {
        "denoising_steps": np.int64(4),
        "context_refresh": np.True_,
        "refresh_steps": np.array([0, 1]),
        "sink_frames": np.int32(0),
    }
    env = M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(tiny_bundle), config={"model": given})
    plain = StreamingConfig(denoising_steps=4, context_refresh=True, refresh_steps=(0, 1), sink_frames=0)
    assert env.backend.streaming == env.backend.wm.student_cfg.streaming == plain
    assert json.loads(json.dumps(env.backend.streaming.to_dict())) == plain.to_dict()  # Python numbers inside
    env.close()
    with pytest.raises(InvalidOptionError, match=r"config.model.refresh_steps must be .*, got \[\[0, 1\]\]"):
        EnvConfig.from_dict({"model": {"refresh_steps": np.array([[0, 1]])}})
    with pytest.raises(InvalidOptionError, match=r"config.model.refresh_steps must be .*, got \[True\]"):
        EnvConfig.from_dict({"model": {"refresh_steps": np.array([True])}})


@pytest.mark.parametrize(
    ("bad", "field"),
    [
        ({"denoising_steps": True}, "denoising_steps"),
        ({"refresh_steps": "01"}, "refresh_steps"),
        ({"context_refresh": "yes"}, "context_refresh"),
        ({"first_frame_guidance": True}, "first_frame_guidance"),
        ({"first_frame_guidance": "2"}, "first_frame_guidance"),
        ({"sinks": 1}, "unknown keys"),
    ],
)
def test_bad_values_name_the_file_and_field(bad, field):
    with pytest.raises(ValueError, match=f"my.json.*{field}"):
        StreamingConfig.from_dict(bad, "my.json")


def test_round_trip_and_a_null_refresh_steps_reading_as_every_step():
    s = StreamingConfig(denoising_steps=2, refresh_steps=(-1,), sink_frames=0)
    assert StreamingConfig.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    every = StreamingConfig(refresh_steps=REFRESH_EVERY_STEP)
    assert StreamingConfig.from_dict({**every.to_dict(), "refresh_steps": None}) == every
    # A file keeps refresh steps while its refresh is off (the refresh steps to use once it is on).
    off = {"context_refresh": False, "refresh_steps": [-2, -1]}
    assert StreamingConfig.from_dict(off).resolved_refresh_steps() == ()


def test_a_resets_first_frame_takes_the_first_frame_steps_and_guidance(bundle, monkeypatch):
    """The reference model samples an episode's first frame in the bundle's first_frame_steps and
    first_frame_guidance, or the env config's, single env and vector env alike."""
    from world_model.model.reference import ReferenceGenerator

    taken = []
    sample = ReferenceGenerator.sample

    def counted(self, cond, extra=None, steps=None, seed=0, sampler=None, guidance=None):
        taken.append((steps, guidance))
        return sample(self, cond, extra, steps, seed, sampler, guidance)

    monkeypatch.setattr(ReferenceGenerator, "sample", counted)
    set_streaming(bundle, StreamingConfig(first_frame_steps=3, first_frame_guidance=1.5))
    M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(bundle)).reset(seed=0)
    config = {"model": {"first_frame_steps": 2, "first_frame_guidance": 4}}
    M4WorldEnv("highway_sunny_day", backend="world_model", checkpoint=str(bundle), config=config).reset(seed=0)
    vector = M4WorldVectorEnv(2, "highway_sunny_day", backend="world_model", checkpoint=str(bundle))
    vector.reset(seed=0)
    assert taken[:3] == [(3, 1.5), (2, 4.0), (3, 1.5)] and set(taken[3:]) <= {(3, 1.5)}  # a call a group


def test_bundle_carries_a_verified_streaming_file(bundle):
    root = bundle
    assert json.loads((root / STREAMING_FILE).read_text()) == StreamingConfig().to_dict()
    set_streaming(root, StreamingConfig(sink_frames=0, refresh_steps="all"))
    wm = load_world_model(str(root))
    assert wm.streaming == wm.student_cfg.streaming == StreamingConfig(sink_frames=0, refresh_steps="all")
    (root / STREAMING_FILE).write_text(json.dumps({**StreamingConfig().to_dict(), "sink_frames": 65}))
    with pytest.raises(CheckpointError, match="digest"):
        load_bundle_files(root)
    reseal_bundle(root)  # a sealed file out of bounds: refused by its path and key, before any weights load
    with pytest.raises(CheckpointError, match=r"streaming.json: sink_frames must be an integer in \[0, 64\], got 65"):
        load_world_model(str(root))


def test_cli_shows_and_writes_a_bundles_streaming(bundle, capsys):
    root = bundle
    assert main(["streaming", "--checkpoint", str(root)]) == 0
    assert json.loads(capsys.readouterr().out) == StreamingConfig().to_dict()
    write = ["--refresh-steps", "all", "--sink-frames", "0", "--write"]
    assert main(["streaming", "--checkpoint", str(root), *write]) == 0
    assert load_world_model(str(root)).streaming == StreamingConfig(refresh_steps="all", sink_frames=0)
