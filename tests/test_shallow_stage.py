"""The shallow stage: the run's finished student distilled into fewer blocks, from the CLI and the
recipe's phase, into a bundle; its loss and its refusals."""

import shutil
from dataclasses import replace

import pytest
import torch

from tests.model_fixtures import QUIET
from world_model.bundle import export_bundle, load_bundle_files
from world_model.model import get_preset
from world_model.streaming import taught_streaming
from world_model.train import stage_options, train_stage
from world_model.train.exports import load_student
from world_model.train.shallow_stage import mimic_loss

from .model_fixtures import make_dataset, one_streamed_chunk, train_cli


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run whose finished student is a (barely) trained 2-block student, as a seeded bundle's
    ``RUN/long``."""
    root = tmp_path_factory.mktemp("shallow")
    data = make_dataset(root / "data", get_preset("tiny"), lengths=(4, 3))
    for stage in ("vae", "teacher", "tf"):
        train_stage(stage, data, root / "run", stage_options(stage, preset="tiny", steps=2, ckpt_every=2), QUIET)
    shutil.copytree(root / "run" / "tf", root / "run" / "long", ignore=shutil.ignore_patterns("checkpoints"))
    return data, root / "run"


def _private(run, tmp_path):
    data, rundir = run
    mine = tmp_path / "run"
    for stage in ("vae", "long"):
        shutil.copytree(rundir / stage, mine / stage, ignore=shutil.ignore_patterns("checkpoints"))
    return data, mine


def test_mimic_loss_is_the_mean_squared_difference():
    a = torch.zeros(2, 1, 3, 4, 2, 2)
    b = torch.full_like(a, 0.5)
    assert mimic_loss(a, a) == 0
    assert mimic_loss(a.bfloat16(), b) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="differ in shape"):
        mimic_loss(a, b[:1])


def test_shallow_stage_from_the_cli_exports_a_shallower_student_that_streams_and_resumes(run, tmp_path):
    data, mine = _private(run, tmp_path)
    common = ["--stage", "shallow", "--data", str(data), "--run", str(mine), "--student-depth", "1"]
    out = train_cli(*common, "--steps", "2", "--ckpt-every", "1", "--batch-size", "2")
    assert out["step"] == 2 and out["resumed_from"] is None
    assert all(torch.isfinite(torch.tensor(out["final_loss"])).reshape(-1))
    again = train_cli(*common, "--steps", "3", "--ckpt-every", "1", "--batch-size", "2")
    assert again["resumed_from"] == 2 and again["step"] == 3

    student, scfg = load_student(mine / "shallow" / "model")
    deep, deep_scfg = load_student(mine / "long" / "model")
    assert len(student.blocks) == 1 and len(deep.blocks) == 2
    # the settings it was trained under: the deep student's, streaming as the env streams it
    assert scfg == replace(deep_scfg, streaming=taught_streaming(deep_scfg.num_steps))
    latents = one_streamed_chunk(student, scfg)
    assert latents.shape == (2, *student.cfg.latent_shape(1)) and torch.isfinite(latents).all()

    # The bundle's student is the shallow one, its config at the shallow depth.
    bundle = load_bundle_files(export_bundle(mine, tmp_path / "bundle"))
    assert bundle.manifest["components"]["student"]["stage"] == "shallow"
    assert bundle.model_config["dit"]["depth"] == 1
    assert len({k.split(".")[1] for k in bundle.tensors["student"] if k.startswith("blocks.")}) == 1


def test_shallow_student_comes_closer_to_the_deep_one(run, tmp_path):
    from safetensors.torch import load_file, save_file

    data, mine = _private(run, tmp_path)
    # The block the shallow student drops made to matter: the barely trained one adds next to nothing.
    export = mine / "long" / "model.safetensors"
    gen = torch.Generator().manual_seed(0)
    state = {
        k: v + torch.randn(v.shape, generator=gen) if k.startswith("blocks.0.") and v.ndim == 2 else v
        for k, v in load_file(export).items()
    }
    save_file(state, export)
    config = _depth(get_preset("tiny"), 1)
    options = stage_options("shallow", preset="tiny", config=config, steps=40, batch_size=2, lr=3e-3, ckpt_every=40)
    losses = train_stage("shallow", data, mine, options, QUIET)["losses"]
    assert sum(losses[-10:]) < 0.5 * sum(losses[:10]), losses


def _depth(cfg, depth):
    from world_model.model.config import with_student_settings

    return with_student_settings(cfg, depth)


@pytest.mark.parametrize("depth", [None, 2])
def test_shallow_stage_refuses_a_depth_not_below_the_students(run, tmp_path, depth):
    data, mine = _private(run, tmp_path)
    options = stage_options("shallow", preset="tiny", steps=1, config=_depth(get_preset("tiny"), depth))
    with pytest.raises(ValueError, match="fewer blocks than the run's student's 2: give --student-depth below 2"):
        train_stage("shallow", data, mine, options, QUIET)


def test_shallow_stage_needs_a_finished_student(run, tmp_path):
    data, rundir = run
    mine = tmp_path / "run"
    shutil.copytree(rundir / "vae", mine / "vae")
    options = stage_options("shallow", preset="tiny", steps=1, config=_depth(get_preset("tiny"), 1))
    with pytest.raises(FileNotFoundError, match="train --stage long"):
        train_stage("shallow", data, mine, options, QUIET)


def test_the_run_student_streams_as_its_bundle_would(run, tmp_path):
    """The stages that stream the run's student (the shallow stage's deep student, the decoder
    stages' rollouts) stream it as a bundle exported from the run streams it: the defaults at its
    taught denoising steps, not the settings it was trained under nor the 4-step defaults."""
    import json
    from types import SimpleNamespace

    from world_model.streaming import StreamingConfig
    from world_model.train.rollout_decoder_stage import run_student
    from world_model.train.shallow_stage import deep_student

    _, mine = _private(run, tmp_path)
    meta_file = mine / "long" / "model.json"
    meta = json.loads(meta_file.read_text())
    meta["student_config"]["streaming"] |= {"denoising_steps": 1, "sink_frames": 0, "refresh_steps": "all"}
    meta_file.write_text(json.dumps(meta))
    _, deep_scfg, stage = deep_student(mine)
    _, rolled_scfg = run_student(SimpleNamespace(run_dir=mine))
    assert stage == "long"
    assert deep_scfg.streaming == rolled_scfg.streaming == taught_streaming(1) != StreamingConfig()
    assert taught_streaming(1).sink_frames == StreamingConfig().sink_frames == 1

    # The decoder stages roll out the student the run's bundle carries: a shallow one where there is one.
    shutil.copytree(mine / "long", mine / "shallow")
    meta["student_config"]["streaming"]["denoising_steps"] = 2
    (mine / "shallow" / "model.json").write_text(json.dumps(meta))
    assert run_student(SimpleNamespace(run_dir=mine))[1].streaming == taught_streaming(2)
