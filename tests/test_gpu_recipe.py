"""The GPU recipe's command, dry-run on the CPU: tiny preset, a few steps per stage, same code path."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import pytest

import m4world_env  # noqa: F401  (registers M4World-v0)
from world_model.train.recipe import (
    ADAPTERS,
    BUNDLE_RESERVE_S,
    CHAIN,
    PHASES,
    SCALES,
    TIME_SHARES,
    join_files,
    stage_time_limit,
)

ROOT = Path(__file__).resolve().parents[1]


def test_the_gpu_recipe_dry_run_records_trains_the_chain_and_writes_a_split_bundle(tmp_path):
    out = tmp_path / "recipe"
    cmd = [sys.executable, "-m", "world_model.train.recipe", "--out", str(out), "--scale", "dry"]
    cmd += ["--device", "cpu", "--workers", "2", "--no-progress", "--max-file-mib", "0.25"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "recipe.json").read_text())
    assert summary["clips"] == 9 and set(summary["final_loss"]) == set(PHASES)
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
    spec = replace(SCALES["dry"], time_limit_s=100.0 + BUNDLE_RESERVE_S)
    first = stage_time_limit(spec, PHASES, elapsed_s=0.0)
    assert first == pytest.approx(100.0 * TIME_SHARES["vae"] / sum(TIME_SHARES.values()))
    # the last stage gets everything that is left, whatever the earlier stages took
    assert stage_time_limit(spec, PHASES[-1:], elapsed_s=70.0) == pytest.approx(30.0)
    assert stage_time_limit(spec, PHASES[-1:], elapsed_s=500.0) == 1.0  # over time: one more short try
    assert stage_time_limit(SCALES["dry"], PHASES, elapsed_s=0.0) is None  # no limit: steps decide


def test_each_scale_trains_the_layout_design_with_a_text_encoder_its_machine_has():
    from world_model.model.config import get_preset
    from world_model.train.recipe import LAYOUT_SUPERSAMPLE, recipe_config

    for name, spec in SCALES.items():
        cfg = recipe_config(spec)
        assert cfg.layout.enabled and cfg.layout.supersample == LAYOUT_SUPERSAMPLE, name
        assert cfg.text.dim == get_preset(spec.preset).text.dim, name
        assert set(spec.stages) == {*CHAIN, "lora"}, name
    # the GPU machine cannot download MiniLM; this CPU has it and keeps the preset's encoder
    assert recipe_config(SCALES["gpu"]).text.encoder == "hash"
    assert recipe_config(SCALES["cpu"]).text.encoder == get_preset("default").text.encoder == "minilm"
