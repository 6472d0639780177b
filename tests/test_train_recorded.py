"""Training on what `m4world record` writes (not the synthetic fixture dataset), and a teacher run
killed mid-way that resumes from its last checkpoint."""

import json

import pytest

from m4world_env.cli import main
from tests.model_fixtures import QUIET, kill_after_checkpoint
from world_model.data import list_clips, read_clip
from world_model.model import get_preset
from world_model.train import load_latest, stage_options, train_stage


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("recorded")
    args = ["record", "--preset", "tiny", "--scenario", "merge_cut_in", "roundabout_fog", "--duration", "0.8"]
    assert main([*args, "--out", str(out)]) == 0
    return out


def test_record_preset_matches_the_model_sensors(recorded):
    sensors = get_preset("tiny").sensors
    clip = read_clip(recorded, list_clips(recorded)[0])
    assert clip.cameras.shape[1:] == (sensors.num_cameras, sensors.height, sensors.width, 3)
    assert clip.lidar.shape[1:] == (sensors.lidar.beams, sensors.lidar.azimuth)
    assert clip.bev.shape[1:] == sensors.bev.shape


def test_vae_and_teacher_train_on_recorded_clips_and_a_killed_teacher_resumes(recorded, tmp_path, capsys):
    run = tmp_path / "run"
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--run", str(run), "--no-progress"]
    assert main([*base, "--stage", "vae", "--steps", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 2
    # The teacher, as a separate process, killed once it has checkpointed twice.
    args = ["--stage", "teacher", "--data", str(recorded), "--run", str(run), "--preset", "tiny"]
    kill_after_checkpoint(
        [*args, "--steps", "100000", "--ckpt-every", "2", "--no-progress"], run / "teacher" / "checkpoints"
    )
    ck = load_latest(run / "teacher" / "checkpoints")
    assert ck is not None and ck.step >= 4
    out = train_stage(
        "teacher", recorded, run, stage_options("teacher", preset="tiny", steps=ck.step + 2, ckpt_every=2), QUIET
    )
    assert out["resumed_from"] == ck.step and out["step"] == ck.step + 2
    assert (run / "teacher" / "model.safetensors").exists()
