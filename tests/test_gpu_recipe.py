"""The GPU recipe's command, dry-run on the CPU: tiny preset, a few steps per stage, same code path."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import traceback
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401  (registers M4World-v0)
from world_model.train import StageRuntime, train_stage
from world_model.train.device import TrainPlace
from world_model.train.recipe import (
    ADAPTERS,
    BUNDLE_RESERVE_S,
    CHAIN,
    DEFAULT_PHASES,
    OPTIONAL_PHASES,
    PHASES,
    SCALES,
    join_files,
    phase_options,
    rare_dir,
    recipe_config,
    stage_time_limit,
)
from world_model.train.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dry_recipe(tmp_path_factory):
    """The recipe's command at the dry scale: its output folder (data, run, bundle, bundle_parts)."""
    out = tmp_path_factory.mktemp("dry") / "recipe"
    cmd = [sys.executable, "-m", "world_model.train.recipe", "--out", str(out), "--scale", "dry"]
    cmd += ["--device", "cpu", "--workers", "2", "--no-progress", "--max-file-mib", "0.25"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def test_the_gpu_recipe_dry_run_records_trains_the_chain_and_writes_a_split_bundle(dry_recipe, tmp_path):
    out = dry_recipe
    summary = json.loads((out / "recipe.json").read_text())
    assert summary["clips"] == 9 and set(summary["final_loss"]) == set(DEFAULT_PHASES)
    assert all(v == v for v in summary["final_loss"].values())  # finite, not NaN
    manifest = json.loads((out / "bundle" / "manifest.json").read_text())
    assert {"vae", "student", "reference"} <= set(manifest["components"])
    assert manifest["components"]["student"]["stage"] == "long"
    parts = [p for p in (out / "bundle_parts").rglob("*") if p.is_file()]
    assert max(p.stat().st_size for p in parts) <= 0.25 * (1 << 20)
    assert any(".part" in p.name for p in parts)  # the student is larger than 0.25 MiB: split
    join_files(out / "bundle_parts", tmp_path / "joined")
    for file in (out / "bundle").rglob("*"):
        if file.is_file():
            assert (tmp_path / "joined" / file.relative_to(out / "bundle")).read_bytes() == file.read_bytes()
    assert sorted(p.name for p in (out / "bundle" / "adapters").iterdir()) == sorted(ADAPTERS)
    # the rare object's scenario names the completion adapter: it loads on the bundle it was trained on
    env = gym.make(
        "M4World-v0", scenario="tree_truck_highway", backend="world_model", checkpoint=str(tmp_path / "joined")
    )
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(env.action_space.sample())
    assert obs["cameras"].shape[0] == manifest["model_config"]["sensors"]["num_cameras"]
    assert manifest["model_config"]["text"]["encoder"] == "hash"  # no download on the GPU machine
    env.close()


def test_stage_time_limits_share_what_is_left_and_pass_on_what_a_stage_did_not_use():
    spec = replace(SCALES["gpu"], time_limit_s=100.0 + BUNDLE_RESERVE_S)
    weights = spec.phase_seconds
    first = stage_time_limit(spec, PHASES, elapsed_s=0.0)
    assert first == pytest.approx(100.0 * weights["vae"] / sum(weights.values()))
    # the last stage gets everything that is left, whatever the earlier stages took
    assert stage_time_limit(spec, PHASES[-1:], elapsed_s=70.0) == pytest.approx(30.0)
    assert stage_time_limit(spec, PHASES[-1:], elapsed_s=500.0) == 1.0  # over time: one more short try
    assert stage_time_limit(SCALES["dry"], PHASES, elapsed_s=0.0) is None  # no limit: steps decide
    for name, scale in SCALES.items():  # a scale with a time limit weighs every phase
        assert scale.time_limit_s is None or set(scale.phase_seconds) == set(PHASES), name
    unweighed = replace(SCALES["dry"], time_limit_s=100.0 + BUNDLE_RESERVE_S)  # --time-limit-s on the dry scale
    assert stage_time_limit(unweighed, PHASES, elapsed_s=0.0) == pytest.approx(100.0 / len(PHASES))


def test_each_scale_trains_the_layout_design_with_a_text_encoder_its_machine_has():
    from world_model.model.config import get_preset
    from world_model.train.recipe import LAYOUT_SUPERSAMPLE, recipe_config

    for name, spec in SCALES.items():
        cfg = recipe_config(spec)
        assert cfg.layout.enabled and cfg.layout.supersample == LAYOUT_SUPERSAMPLE, name
        assert cfg.text.dim == get_preset(spec.preset).text.dim, name
        assert set(spec.stages) == {*CHAIN, *OPTIONAL_PHASES, "lora"}, name
    # the GPU machine cannot download MiniLM; this CPU has it and keeps the preset's encoder
    assert recipe_config(SCALES["gpu"]).text.encoder == "hash"
    assert recipe_config(SCALES["cpu"]).text.encoder == get_preset("default").text.encoder == "minilm"


class HostGenerator(torch.Generator):
    """A CPU generator whatever device is asked for."""

    def __new__(cls, device: object = None):
        return super().__new__(cls)

    def __init__(self, device: object = None) -> None:
        pass


@pytest.mark.parametrize("phase", PHASES)
def test_every_stage_trains_with_the_model_on_another_device(dry_recipe, tmp_path, phase, monkeypatch):
    """Each stage of the chain, from the dry run's earlier stages, trains its first step with the
    training device on ``meta``: mixing a tensor there with a CPU tensor fails as it does on a GPU,
    so a batch, noise or label map left on the CPU shows here. A step gets as far as its first read
    of a value back to the host (``float(loss)``; the ode stage's teacher sampling reads its time
    grid, the first_frame stage's reference sampling its times, the shallow stage's streaming which
    denoising step refreshes the context), which ``meta`` cannot answer."""
    monkeypatch.setattr(torch, "Generator", HostGenerator)  # meta has no generator
    for draw in ("rand", "randn", "randint"):  # drawn on the CPU, then moved, as the runtime's noise
        real = getattr(Trainer, draw)
        monkeypatch.setattr(Trainer, draw, lambda self, *a, _real=real: _real(self, *a).to(self.place.device))
    work = tmp_path / "recipe"
    shutil.copytree(dry_recipe, work, symlinks=True)
    stage = "lora" if phase in ADAPTERS else phase
    for p in (work / "run" / stage).glob("*"):  # the stage trains anew; the run's caches stay
        if p.name not in ("latents", "layouts", "labels", "rollouts.pt"):
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    spec = SCALES["dry"]
    options = phase_options(phase, spec, recipe_config(spec), 0, work / "data", work / "bundle")
    runtime = StageRuntime(progress=False, place=TrainPlace(torch.device("meta")))
    with pytest.raises((RuntimeError, NotImplementedError), match="meta tensor") as raised:
        train_stage(stage, work / "data", work / "run", replace(options, steps=1), runtime)
    own = [f for f in traceback.extract_tb(raised.value.__traceback__) if "world_model" in f.filename]
    host_reads = ("trainer.py", "student_stages.py", "flow.py", "sampler.py", "engine.py")
    assert Path(own[-1].filename).name in host_reads, own[-1]


def test_phases_of_a_finished_bundle_retrain_from_it_and_leave_the_rest_as_it_was(dry_recipe, tmp_path):
    from safetensors.torch import load_file

    from world_model.train.recipe import RecipeOptions, run_recipe
    from world_model.train.seed_run import seed_run

    out = tmp_path / "again"
    shutil.copytree(dry_recipe / "data", out / "data")  # recorded: the recipe skips them
    shutil.copytree(rare_dir(dry_recipe / "data"), rare_dir(out / "data"))
    source = dry_recipe / "bundle"
    phases = ("rollout_decoder", "range_head", "camera_decoder")
    for cut, refused in ((1, "range_head"), (2, "camera_decoder")):  # each finishes or keeps the one before
        with pytest.raises(ValueError, match=f"--phases {' '.join(phases[:cut])} {refused}"):
            options = RecipeOptions("dry", "cpu", workers=1, progress=False, from_bundle=source, phases=phases[:cut])
            run_recipe(out, options)
    options = RecipeOptions("dry", "cpu", workers=1, progress=False, from_bundle=source, phases=phases)
    summary = run_recipe(out, options)
    assert summary["phases"] == list(phases) and set(summary["final_loss"]) == set(phases)
    manifest = json.loads((out / "bundle" / "manifest.json").read_text())
    assert manifest["components"]["vae"]["stage"] == "camera_decoder"
    for component in ("student", "reference"):  # untouched: the same tensors as the bundle it started from
        old, new = (load_file(str(b / f"{component}.safetensors")) for b in (source, out / "bundle"))
        assert old.keys() == new.keys() and all(torch.equal(old[k], new[k]) for k in old)
    old, new = (load_file(str(b / "vae.safetensors")) for b in (source, out / "bundle"))
    assert all(torch.equal(old[k], new[k]) for k in old if k.startswith("encoder."))  # the latents stay
    assert any(not torch.equal(old[k], new[k]) for k in old if k.startswith("decoder.label_mods."))  # trained
    assert sorted(p.name for p in (out / "bundle" / "adapters").iterdir()) == sorted(ADAPTERS)
    seeded = json.loads((out / "run" / "decoder" / "model.json").read_text())
    assert seeded["seeded_from"] == str(source)
    assert seed_run(source, out / "run") == []  # a seeded run keeps what it has
    with pytest.raises(ValueError, match="--phases"):
        run_recipe(out, replace(options, from_bundle=None, phases=("paint",)))
    with pytest.raises(ValueError, match="--episodes must be a positive integer, got 0"):
        run_recipe(out, replace(options, episodes=0))


TUNED = {"command": "m4world tune-range-head", "frames": 3}  # a range head's record, as the shipped bundle's


def recorded_run_from_a_tuned_bundle(dry_recipe: Path, out: Path) -> tuple[Path, Path]:
    """``out`` with the dry recipe's recorded clips (the recipe skips recording them), and a copy of
    its bundle whose manifest records its range head's tuning, beside ``out``."""
    from world_model.bundle import reseal_bundle

    shutil.copytree(dry_recipe / "data", out / "data")
    shutil.copytree(rare_dir(dry_recipe / "data"), rare_dir(out / "data"))
    source = shutil.copytree(dry_recipe / "bundle", out.with_name(out.name + "_source"))
    manifest_path = source / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["components"]["vae"]["tuned"] = TUNED
    manifest_path.write_text(json.dumps(manifest))
    reseal_bundle(source)
    return out, source


def test_a_finished_bundle_taught_fewer_steps_streams_at_them(dry_recipe, tmp_path):
    from safetensors.torch import load_file

    from world_model.train.recipe import RecipeOptions, run_recipe

    out, source = recorded_run_from_a_tuned_bundle(dry_recipe, tmp_path / "steps")
    options = RecipeOptions("dry", "cpu", workers=1, progress=False, from_bundle=source, phases=("steps",), episodes=1)
    summary = run_recipe(out, options)
    assert summary["steps"] == {"steps": 2} and summary["clips"] == 9
    teacher = json.loads((out / "run" / "teacher" / "model.json").read_text())
    assert teacher["cut_from"] == "reference" and teacher["model_config"]["dit"]["in_channels_extra"] == 0
    manifest = json.loads((out / "bundle" / "manifest.json").read_text())
    assert manifest["components"]["student"]["stage"] == "steps"
    assert manifest["components"]["vae"]["tuned"] == TUNED
    assert "tuned" not in manifest["components"]["student"]
    assert manifest["student_config"]["streaming"]["denoising_steps"] == 2  # half the long student's 4
    streaming = json.loads((out / "bundle" / "streaming.json").read_text())
    assert streaming["denoising_steps"] == 2 and streaming["refresh_steps"] == [-2, -1]
    old, new = (load_file(str(b / "student.safetensors")) for b in (source, out / "bundle"))
    assert any(not torch.equal(old[k], new[k]) for k in old)
    again = run_recipe(tmp_path / "again", replace(options, from_bundle=out / "bundle"))  # halved once more
    assert again["steps"] == {"steps": 2}
    assert json.loads((tmp_path / "again" / "bundle" / "streaming.json").read_text())["denoising_steps"] == 1
    env = gym.make("M4World-v0", scenario="highway_sunny_day", backend="world_model", checkpoint=str(out / "bundle"))
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(env.action_space.sample())
    assert np.isfinite(obs["lidar"]).all()
    env.close()


def test_the_camera_decoder_of_a_finished_bundle_retrains_leaving_the_lidar_bit_for_bit(dry_recipe, tmp_path):
    from safetensors.torch import load_file

    from world_model.train.recipe import RecipeOptions, run_recipe

    out, source = recorded_run_from_a_tuned_bundle(dry_recipe, tmp_path / "cameras")
    options = RecipeOptions("dry", "cpu", workers=1, progress=False, from_bundle=source, phases=("camera_decoder",))
    run_recipe(out, options)
    manifest = json.loads((out / "bundle" / "manifest.json").read_text())
    assert manifest["components"]["vae"]["stage"] == "camera_decoder"
    assert manifest["components"]["vae"]["tuned"] == TUNED  # its head's
    assert manifest["model_config"]["layout"]["camera_decoder"] and manifest["model_config"]["layout"]["range_head"]
    old, new = (load_file(str(b / "vae.safetensors")) for b in (source, out / "bundle"))
    assert old.keys() == new.keys()
    lidar_path = [k for k in old if not k.startswith("camera_decoder.")]
    assert all(torch.equal(old[k], new[k]) for k in lidar_path)  # encoder, LiDAR decoder, range head
    # a copy of the LiDAR's decoder, trained (the dry run's few frames may show no vehicle, which
    # leaves it as it was: tests/test_camera_decoder.py checks what it learns)
    cameras = [k for k in new if k.startswith("camera_decoder.")]
    assert cameras and all(new[k].shape == new[k.replace("camera_", "", 1)].shape for k in cameras)
    assert json.loads((out / "recipe.json").read_text())["steps"]["camera_decoder"] > 0
