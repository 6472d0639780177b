"""The shipped default checkpoint: in the package, verified, and what `make demo` runs on."""

import json

import pytest

from m4world_env.cli import main
from world_model.bundle import DEFAULT_BUNDLE, load_bundle_files


def test_default_bundle_is_package_data_and_verifies():
    files = load_bundle_files(None)  # None = the shipped bundle; checks every sha256 of the manifest
    assert files.path == DEFAULT_BUNDLE
    assert {"vae", "student", "reference"} <= set(files.tensors)
    assert files.manifest["components"]["student"]["stage"] in ("shallow", "steps", "long", "dmd")
    size = sum(p.stat().st_size for p in DEFAULT_BUNDLE.rglob("*") if p.is_file())
    assert size <= 100 * 2**20  # the shipped weights stay under 100 MB


@pytest.mark.slow
def test_demo_runs_on_the_shipped_checkpoint(tmp_path, capsys):
    out = tmp_path / "demo.mp4"
    assert main(["demo", "--steps", "2", "--out", str(out)]) == 0
    assert out.stat().st_size > 0
    printed = capsys.readouterr().out
    assert "backend world_model" in printed and "episode score" in printed
    assert "DiT dtype float32" in printed or "DiT dtype bfloat16" in printed  # what dtype "auto" chose
    assert json.loads((DEFAULT_BUNDLE / "manifest.json").read_text())["format"] == "m4world-bundle"


def test_demo_refuses_an_output_that_is_no_video_before_running(tmp_path, capsys):
    kept = tmp_path / "results"
    kept.write_text("an earlier file")
    assert main(["demo", "--steps", "2", "--out", str(kept)]) == 2
    assert "give a video file ending in .mp4" in capsys.readouterr().err
    assert kept.read_text() == "an earlier file"
    assert main(["demo", "--steps", "2", "--out", str(tmp_path)]) == 2  # a folder


def test_every_shipped_adapter_fits_a_model_of_the_shipped_bundle():
    """adapters/: tree_truck_completion (the reference model's, for object completion: it completes
    tree trucks at reset) loads by name into the model it was trained on."""
    from world_model.lora import loaded_adapters, read_adapter
    from world_model.rollout.runtime import load_world_model

    wm = load_world_model(None, dtype="float32")
    names = sorted(p.name for p in (DEFAULT_BUNDLE / "adapters").iterdir() if p.is_dir())
    assert names == ["tree_truck_completion"]
    assert wm.apply_adapters(names) == ["tree_truck_completion"]
    assert loaded_adapters(wm.reference) == ["tree_truck_completion"]
    assert read_adapter(DEFAULT_BUNDLE / "adapters" / names[0])[0].completes == "tree_truck"


def test_a_scenario_whose_steps_split_a_chunk_is_refused_at_construction():
    from m4world_env.config import InvalidOptionError
    from m4world_env.env import M4WorldEnv
    from m4world_env.scenario import load_scenario

    one_frame_steps = load_scenario("merge_cut_in").model_copy(update={"policy_frequency": 10})
    with pytest.raises(InvalidOptionError, match="2-frame chunks"):  # the default checkpoint's chunks
        M4WorldEnv(one_frame_steps, backend="world_model")
