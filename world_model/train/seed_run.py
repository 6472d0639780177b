"""Start a run from a bundle: its components written as the stage exports that made them.

A later stage then trains on them as it would on the run that exported the bundle, e.g. the decoder
stages again on a shipped checkpoint whose DiTs stay as they are::

    RUN/vae/        the bundle's encoder with its decoder's plain trunk (the latents every stage reads)
    RUN/decoder/    the bundle's VAE as it is, label modulations included (a decoder stage's start),
                    without its range head
    RUN/camera_decoder/ the bundle's VAE as it is, when it draws the cameras with a decoder of their own
    RUN/range_head/ the bundle's VAE without a camera decoder, when it has a range head
    RUN/<stage>/    the student, under the stage that exported it (``long``), with its student config;
                    a student of the ``steps`` stage also as ``RUN/long`` (the stage it starts from)
    RUN/reference/  the reference model, under its own config
    RUN/teacher/    the reference model without its reference channels (a bundle has no teacher:
                    :func:`~world_model.model.reference.teacher_from_reference`), the real score of
                    the ``steps`` stage
    RUN/first_frame/  the one-step first-frame model, under its own config (the reference model's)
    RUN/lora/NAME/  the adapters

Each export keeps what its component's manifest entry records of how it was made (the range head's
tuning, :func:`~world_model.bundle.bundle_record`), which a bundle exported from the run carries on
while the export is the seeded one. Exports already in the run are kept: seeding a run that has
trained since leaves its work alone.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import torch

from world_model.bundle import BUNDLE_RECORD, bundle_record, load_bundle_files
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.dit import MultiViewDiT
from world_model.model.range_head import finished_digest
from world_model.model.reference import teacher_from_reference
from world_model.model.vae import SensorVAE
from world_model.train.checkpoint import export_weights
from world_model.train.exports import EXPORT

SEEDED_FROM = "seeded_from"  # the export's metadata: the bundle it came from


def _float32(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The bundle stores its DiTs in bf16; training reads float32 (bf16 -> float32 is exact)."""
    return {k: v.float() if v.is_floating_point() else v for k, v in state.items()}


def seed_run(bundle: str | Path, run_dir: str | Path) -> list[str]:
    """Write ``bundle``'s components into ``run_dir`` as stage exports (module docstring); returns the
    stages written (those the run already had are skipped)."""
    files = load_bundle_files(bundle)
    run_dir = Path(run_dir)
    cfg = ModelConfig.from_dict(files.model_config)
    source = {SEEDED_FROM: str(files.path)}
    written: list[str] = []

    def export(stage: str, state: dict[str, torch.Tensor], meta: dict) -> None:
        path = run_dir / stage / EXPORT
        if path.with_suffix(".safetensors").exists():
            return
        export_weights(path, state, {"stage": stage, **meta, **source})
        written.append(stage)

    vae = files.tensors["vae"]
    records = {c: {BUNDLE_RECORD: bundle_record(e)} for c, e in files.manifest["components"].items()}
    if cfg.layout.camera_decoder:
        export("camera_decoder", vae, {"model_config": cfg.to_dict(), **records["vae"]})
        cfg = replace(cfg, layout=replace(cfg.layout, camera_decoder=False))
        vae = {k: v for k, v in vae.items() if not k.startswith("camera_decoder.")}
    if cfg.layout.range_head:
        meta = {"model_config": cfg.to_dict(), "finishes": finished_digest(vae), **records["vae"]}
        export("range_head", vae, meta)
    if cfg.layout.decoder:
        decoder_cfg = replace(cfg, layout=replace(cfg.layout, range_head=False))
        decoder = SensorVAE(decoder_cfg).state_dict()
        export("decoder", {k: vae[k] for k in decoder}, {"model_config": decoder_cfg.to_dict()})
    plain_cfg = without_label_decoder(cfg)
    plain = SensorVAE(plain_cfg).state_dict()
    export("vae", {k: vae[k] for k in plain}, {"model_config": plain_cfg.to_dict()})
    student_stage = files.manifest["components"]["student"]["stage"]
    student_meta = {
        "model_config": files.model_config,
        "student_config": files.manifest.get("student_config") or {},
        **records["student"],
    }
    export(student_stage, _float32(files.tensors["student"]), student_meta)
    if student_stage == "steps":  # the steps stage starts from RUN/long: a taught student can be halved again
        export("long", _float32(files.tensors["student"]), student_meta)
    for component in ("reference", "first_frame"):
        if files.has(component):
            own = files.component_config(component) or files.model_config
            export(component, _float32(files.tensors[component]), {"model_config": own, **records[component]})
    if files.has("reference"):
        reference = MultiViewDiT(ModelConfig.from_dict(files.component_config("reference") or files.model_config))
        reference.load_state_dict(_float32(files.tensors["reference"]))
        teacher = teacher_from_reference(reference)
        export("teacher", teacher.state_dict(), {"model_config": teacher.cfg.to_dict(), "cut_from": "reference"})
    adapters = files.path / "adapters"
    if adapters.is_dir():
        for adapter in sorted(p for p in adapters.iterdir() if p.is_dir()):
            target = run_dir / "lora" / adapter.name
            if not target.exists():
                shutil.copytree(adapter, target)
                written.append(f"lora/{adapter.name}")
    return written
