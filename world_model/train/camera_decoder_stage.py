"""The ``camera_decoder`` stage: the cameras' own decoder, tuned on the student's rollouts.

The ``rollout_decoder`` stage tunes one label decoder for every view, and the ``range_head`` stage
finishes its LiDAR view. A decoder tuned again for the cameras moves the LiDAR view and its range
head with it, and the policies that read the LiDAR score away from the ground truth
(docs/experiments.md). Here the VAE gains a copy of the run's label decoder for the cameras alone
(``layout.camera_decoder``); the copy learns as the ``rollout_decoder`` stage's decoder learns
(half of each batch from the student's rollouts,
:data:`~world_model.train.rollout_decoder_stage.ROLLOUT_SHARE`), on the cameras' frames
only, and only about the vehicles (:class:`~world_model.train.vae_stage.CameraTuning`): the
recording where a vehicle stands and about its bottom edge (those pixels weighing most: where the
car ahead stands on the road is a few rows of a few columns, and a camera policy reads its range
from them), the shared decoder's own drawing elsewhere, so that the road and its markings stay as
the lane finders read them. Every other weight stays bit for bit, so the LiDAR and the range head
that finishes it are the source export's.

    RUN/camera_decoder/rollouts.pt      the student's latents of the rolled-out clips (bf16), reused on resume
    RUN/camera_decoder/model.*          the VAE with its camera decoder (EMA), the bundle's VAE
"""

from __future__ import annotations

import json
from dataclasses import replace

import torch

from world_model.bundle import BUNDLE_RECORD, CAMERA_DECODER_SOURCES
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.vae import SensorVAE
from world_model.sim.labels import LabelRasterizer
from world_model.train.exports import EXPORT, load_vae, require_export, run_vae
from world_model.train.rollout_decoder_stage import rollout_batches, rollout_data, rollout_targets
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer
from world_model.train.vae_stage import (
    CameraTuning,
    check_decoder_config,
    decoder_loss,
    export_vae,
    vae_metrics,
)

STAGE = "camera_decoder"


def with_camera_decoder(cfg: ModelConfig) -> ModelConfig:
    """``cfg`` whose VAE draws the cameras with a decoder of their own."""
    return replace(cfg, layout=replace(cfg.layout, camera_decoder=True))


def load_source(run: StageRun) -> tuple[SensorVAE, dict]:
    """The run's latest label decoder (the first export of
    :data:`~world_model.bundle.CAMERA_DECODER_SOURCES`), range head and all, gaining a camera
    decoder that starts as a copy of its decoder; and the source export's bundle record (how its
    range head was tuned), which holds for the copy's export too: every weight but the camera
    decoder's stays the source's."""
    for stage in CAMERA_DECODER_SOURCES:
        path = run.run_dir / stage / EXPORT
        if path.with_suffix(".safetensors").exists():
            source = load_vae(path)
            if (source.cfg.sensors, source.cfg.vae) != (run.cfg.sensors, run.cfg.vae):
                raise ValueError(f"{path.parent} holds a VAE of another config: train it again with the same --preset")
            vae = SensorVAE(with_camera_decoder(source.cfg))
            missing, unexpected = vae.load_state_dict(source.state_dict(), strict=False)
            if unexpected or any(not k.startswith("camera_decoder.") for k in missing):
                raise ValueError(f"{path.parent} holds a VAE of another config: train it again with the same --preset")
            # The copy has no nearness gate: the cameras read no nearness.
            vae.camera_decoder.load_state_dict(source.decoder.state_dict(), strict=False)
            meta = json.loads(path.with_suffix(".json").read_text())
            return vae, {BUNDLE_RECORD: meta[BUNDLE_RECORD]} if BUNDLE_RECORD in meta else {}
    require_export(run.run_dir / CAMERA_DECODER_SOURCES[-1] / EXPORT, CAMERA_DECODER_SOURCES[-1])
    raise AssertionError("unreachable: require_export raises")


def camera_decoder_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/camera_decoder`` (module docstring)."""
    tcfg = run.tcfg
    check_decoder_config(run.cfg)
    plain, digest = run_vae(run.run_dir, without_label_decoder(run.cfg), STAGE)
    source, record = load_source(run)
    vae = source.to(run.place.device).eval().requires_grad_(False)
    cfg = vae.cfg
    data = rollout_data(run, cfg, plain, digest)
    targets = rollout_targets(vae, data)
    torch.manual_seed(tcfg.seed)
    decoder = vae.camera_decoder.train().requires_grad_(True)
    trainer = run.trainer(decoder, STAGE, model_config=cfg.to_dict())
    draw = rollout_batches(vae, data, tcfg.batch_size, cfg.sensors.num_cameras)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        picks, z = draw(tr)
        return decoder_loss(tr, vae, targets, picks, z, CameraTuning())

    summary = trainer.run(step, STAGE)
    if not run.place.is_main:
        return summary
    decoder.load_state_dict(trainer.ema.model_state(decoder))
    vae = vae.cpu().eval()
    metrics = export_vae(
        run, STAGE, vae, trainer.step, vae_metrics(vae, data.sampler, LabelRasterizer(), targets.styles), **record
    )
    return {**summary, "rollout_clips": len(data.rollouts), "metrics": metrics}
