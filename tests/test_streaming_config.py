"""The bundle's streaming.json: validation, resolution of refresh steps, and its place in the bundle."""

import json

import pytest

from world_model.bundle import STREAMING_FILE, CheckpointError, load_bundle_files, set_streaming
from world_model.runtime import load_world_model
from world_model.student.config import StudentConfig
from world_model.student.streaming import StreamingConfig


def test_defaults_are_what_the_env_runs():
    s = StreamingConfig()
    assert s.diffusion_steps() == (1000, 750, 500, 250)
    assert s.resolved_refresh_steps() == (2, 3) and s.sink_frames == 1
    applied = s.apply(StudentConfig())
    assert (applied.denoising_steps, applied.refresh_steps, applied.sink_frames) == ((1000, 750, 500, 250), (2, 3), 1)


def test_refresh_steps_resolve_against_the_denoising_steps():
    def resolved(**kw) -> tuple[int, ...] | None:
        return StreamingConfig().override(**kw).resolved_refresh_steps()

    assert resolved(denoising_steps=6) == (4, 5)
    assert resolved(denoising_steps=1) == (0,)  # clamped at the first
    assert resolved(refresh_steps=[3, -4, 0]) == (0, 3)  # -4 of 4 is step 0: each step once, in order
    assert resolved(context_refresh=False) is None
    assert StreamingConfig(refresh_steps=None).resolved_refresh_steps() is None  # every step


@pytest.mark.parametrize(
    ("bad", "field"),
    [
        ({"denoising_steps": 0}, "denoising_steps"),
        ({"denoising_steps": True}, "denoising_steps"),
        ({"refresh_steps": [4]}, "refresh_steps"),
        ({"refresh_steps": "01"}, "refresh_steps"),
        ({"refresh_steps": []}, "refresh_steps"),
        ({"sink_frames": -1}, "sink_frames"),
        ({"context_refresh": "yes"}, "context_refresh"),
        ({"sinks": 1}, "unknown keys"),
    ],
)
def test_bad_values_name_the_file_and_field(bad, field):
    with pytest.raises(ValueError, match=f"my.json.*{field}"):
        StreamingConfig.from_dict(bad, "my.json")


def test_round_trip():
    s = StreamingConfig(denoising_steps=2, refresh_steps=(-1,), sink_frames=0)
    assert StreamingConfig.from_dict(json.loads(json.dumps(s.to_dict()))) == s


def test_bundle_carries_a_verified_streaming_file(tiny_bundle, tmp_path):
    import shutil

    root = tmp_path / "bundle"
    shutil.copytree(tiny_bundle, root)
    assert json.loads((root / STREAMING_FILE).read_text()) == StreamingConfig().to_dict()
    set_streaming(root, StreamingConfig(sink_frames=0, refresh_steps=None))
    wm = load_world_model(str(root))
    assert wm.streaming == StreamingConfig(sink_frames=0, refresh_steps=None)
    assert wm.student_cfg.sink_frames == 0 and wm.student_cfg.refresh_steps is None
    (root / STREAMING_FILE).write_text(json.dumps({**StreamingConfig().to_dict(), "sink_frames": 3}))
    with pytest.raises(CheckpointError, match="digest"):
        load_bundle_files(root)


def test_cli_shows_and_writes_a_bundles_streaming(tiny_bundle, tmp_path, capsys):
    import shutil

    from m4world_env.cli import main

    root = tmp_path / "bundle"
    shutil.copytree(tiny_bundle, root)
    assert main(["streaming", "--checkpoint", str(root)]) == 0
    assert json.loads(capsys.readouterr().out) == StreamingConfig().to_dict()
    write = ["--refresh-steps", "all", "--sink-frames", "0", "--write"]
    assert main(["streaming", "--checkpoint", str(root), *write]) == 0
    assert load_world_model(str(root)).streaming == StreamingConfig(refresh_steps=None, sink_frames=0)
