import json

import pytest
import torch
from safetensors.torch import save_file

from world_model.bundle import (
    CheckpointError,
    CheckpointNotFoundError,
    export_bundle,
    load_bundle_files,
)


def _fake_run(root):
    for stage, tensor in (("vae", torch.ones(3)), ("dmd", torch.arange(4.0)), ("reference", torch.zeros(2))):
        d = root / stage
        d.mkdir(parents=True)
        save_file({"w": tensor}, str(d / "model.safetensors"))
        (d / "model.json").write_text(json.dumps({"stage": stage, "model_config": {"name": "tiny"}}))
    return root


def test_export_and_load_roundtrip(tmp_path):
    run = _fake_run(tmp_path / "run")
    own = {"name": "tiny", "dit": {"in_channels_extra": 5}}
    (run / "reference" / "model.json").write_text(json.dumps({"stage": "reference", "model_config": own}))
    adapter = run / "lora" / "tree_truck"
    (adapter / "checkpoints").mkdir(parents=True)
    for name in ("adapter.json", "adapter.safetensors", "model_config.json", "progress.json"):
        (adapter / name).write_text("{}")
    bundle = export_bundle(run, tmp_path / "bundle")
    files = load_bundle_files(bundle)
    assert files.manifest["components"]["student"]["stage"] == "dmd"
    assert torch.equal(files.tensors["student"]["w"], torch.arange(4.0))
    assert files.has("reference") and files.model_config == {"name": "tiny"}
    assert files.component_config("reference") == own and files.component_config("vae") is None
    assert sorted(p.name for p in (bundle / "adapters" / "tree_truck").iterdir()) == [
        "adapter.json",
        "adapter.safetensors",
    ]


def test_the_decoder_stage_gives_the_bundle_its_vae_and_label_maps(tmp_path):
    run = _fake_run(tmp_path / "run")
    plain = load_bundle_files(export_bundle(run, tmp_path / "plain"))
    assert plain.model_config == {"name": "tiny"} and torch.equal(plain.tensors["vae"]["w"], torch.ones(3))
    (run / "decoder").mkdir()
    save_file({"w": torch.full((3,), 2.0)}, str(run / "decoder" / "model.safetensors"))
    files = load_bundle_files(export_bundle(run, tmp_path / "bundle"))
    assert files.manifest["components"]["vae"]["stage"] == "decoder"
    assert torch.equal(files.tensors["vae"]["w"], torch.full((3,), 2.0))
    assert files.model_config == {"name": "tiny", "layout": {"decoder": True}}
    # a student trained for a label decoder, bundled with the plain VAE: the bundle's decoder is plain
    (run / "decoder" / "model.safetensors").unlink()
    student = {"stage": "dmd", "model_config": {"name": "tiny", "layout": {"enabled": True, "decoder": True}}}
    (run / "dmd" / "model.json").write_text(json.dumps(student))
    files = load_bundle_files(export_bundle(run, tmp_path / "plain_vae"))
    assert files.model_config == {"name": "tiny", "layout": {"enabled": True, "decoder": False}}


def test_missing_and_corrupt_checkpoints_are_named(tmp_path):
    with pytest.raises(CheckpointNotFoundError, match="does not exist"):
        load_bundle_files(tmp_path / "nope")
    with pytest.raises(CheckpointError, match="manifest.json is missing"):
        load_bundle_files(tmp_path)
    bundle = export_bundle(_fake_run(tmp_path / "run"), tmp_path / "bundle")
    student = bundle / "student.safetensors"
    data = bytearray(student.read_bytes())
    data[-1] ^= 0xFF
    student.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="student.safetensors is corrupt"):
        load_bundle_files(bundle)
    student.unlink()
    with pytest.raises(CheckpointError, match="student.safetensors is missing"):
        load_bundle_files(bundle)
    (bundle / "manifest.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_bundle_files(bundle)


def test_export_requires_vae_and_student(tmp_path):
    (tmp_path / "run" / "vae").mkdir(parents=True)
    with pytest.raises(CheckpointError, match="student"):
        export_bundle(tmp_path / "run", tmp_path / "b")


def test_export_stores_dits_in_bf16_when_the_model_runs_them_in_bf16(tmp_path):
    run = _fake_run(tmp_path / "run")
    meta = {"stage": "dmd", "model_config": {"name": "tiny", "dit": {"autocast_bf16": True}}}
    (run / "dmd" / "model.json").write_text(json.dumps(meta))
    files = load_bundle_files(export_bundle(run, tmp_path / "bundle"))
    assert files.tensors["student"]["w"].dtype == torch.bfloat16
    assert files.tensors["reference"]["w"].dtype == torch.bfloat16
    assert files.tensors["vae"]["w"].dtype == torch.float32  # the autoencoder is not cast
    assert torch.equal(files.tensors["student"]["w"].float(), torch.arange(4.0))
