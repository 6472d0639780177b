"""The ``rollout_decoder`` stage: the label decoder fine-tuned on the student's own rollouts.

The ``decoder`` stage learns from the encoder's latents, with noise and a synthetic drift added.
The trained student's latents drift in their own way: on some clips a grey sky turns dusk-orange
within a second, and a decoder that never saw such latents draws what they say. Here the run's
student (the one its bundle carries: its ``shallow`` export, else ``steps``, ``long``, ...)
streams :data:`ROLLOUT_CLIPS` training clips once as the env does: the first frame from the run's
reference model (else the student, as a bundle without one), then chunk by chunk with the env's
streaming settings (:func:`~world_model.streaming.taught_streaming`: the defaults at the student's
taught denoising steps, as the run's bundle streams it); the decoder then learns to draw each
recorded frame from the student's latents of it, the frame's label maps and the prompt's style.
:data:`ROLLOUT_SHARE` of every batch comes from these rollouts, the rest is the decoder stage's
batch, so that the decoder keeps following the latents rather than drawing the scene from the label
maps alone.

    RUN/rollout_decoder/rollouts.pt     the student's latents of the rolled-out clips (bf16), reused on resume
    RUN/rollout_decoder/progress.json   clips rolled out so far, then the training's progress
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from world_model.bundle import COMPONENT_STAGES
from world_model.data.clips import Clip, write_json_atomic
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.dit import MultiViewDiT
from world_model.model.reference import ReferenceGenerator, first_frame_sampling
from world_model.model.vae import SensorVAE
from world_model.sim.labels import LabelRasterizer
from world_model.streaming import StreamingConfig, taught_streaming
from world_model.student.config import StudentConfig
from world_model.student.engine import StreamingEngine
from world_model.train.data import FrameSampler, load_clips
from world_model.train.exports import (
    EXPORT,
    latent_windows,
    load_student,
    load_teacher,
    load_vae,
    require_export,
    run_latents,
    run_vae,
)
from world_model.train.rollouts import rollout_conditions
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer
from world_model.train.vae_stage import (
    DecoderTargets,
    check_decoder_config,
    clip_styles,
    decoded_frames,
    decoder_loss,
    decoder_maps,
    export_decoder,
    jittered_latents,
)

STAGE = "rollout_decoder"
# The student rolled out: the one a bundle exported from the run carries (the first that has an export).
STUDENT_STAGES = COMPONENT_STAGES["student"]
ROLLOUT_CLIPS = 32  # training clips rolled out, spread evenly over the dataset (minutes on a CPU)
# Clips streamed together on a CPU, where the work is the same at any batch and a smaller one
# holds less memory; on a GPU a step of a few clips is bound by kernel launches, so all of them
# stream at once.
ROLLOUT_BATCH_CPU = 8
ROLLOUT_SHARE = 0.5  # of each batch: frames of the student's rollouts; the rest as in the decoder stage
ROLLOUTS_FILE = "rollouts.pt"


def rollout_clip_indices(num_clips: int, wanted: int = ROLLOUT_CLIPS) -> list[int]:
    """``wanted`` clip indices spread evenly over ``num_clips`` (all of them when there are fewer):
    the dataset lists each scenario's clips together, so every scenario gets its share."""
    if num_clips <= wanted:
        return list(range(num_clips))
    return [int(i) for i in np.linspace(0, num_clips - 1, wanted).round()]


def run_reference(run: StageRun, stage: str = "reference") -> MultiViewDiT | None:
    """The run's reference model export (``stage``: or its first-frame model's), or None before
    that stage."""
    path = run.run_dir / stage / EXPORT
    return load_teacher(path) if path.with_suffix(".safetensors").exists() else None


def run_first_frames(
    run: StageRun, student: MultiViewDiT, plain: SensorVAE, streaming: StreamingConfig
) -> tuple[ReferenceGenerator, dict]:
    """Who draws a rollout's first frame as the env does, and the keywords of its ``sample``: the
    run's one-step first-frame model where it has one, else its reference model (else the student)
    at ``streaming``'s first-frame settings (:meth:`WorldModel.first_latents
    <world_model.rollout.runtime.WorldModel.first_latents>`)."""
    device = run.place.device
    first = run_reference(run, "first_frame")
    one_step = None if first is None else ReferenceGenerator(first.to(device).eval().requires_grad_(False), plain)
    model = (run_reference(run) or student).to(device).eval().requires_grad_(False)
    return first_frame_sampling(ReferenceGenerator(model, plain), one_step, streaming)


def run_student(run: StageRun) -> tuple[MultiViewDiT, StudentConfig]:
    """The run's latest student export and its :class:`StudentConfig`, streaming as the env does."""
    for stage in STUDENT_STAGES:
        path = run.run_dir / stage / EXPORT
        if path.with_suffix(".safetensors").exists():
            student, scfg = load_student(path)
            return student, replace(scfg, streaming=taught_streaming(scfg.num_steps))
    raise FileNotFoundError(
        f"--stage {STAGE} rolls out the run's student: train --stage {STUDENT_STAGES[-1]} (or a later student "
        f"stage) with the same --run first"
    )


@torch.no_grad()
def student_rollouts(run: StageRun, clips: list[Clip], plain: SensorVAE, digest: str) -> list[torch.Tensor]:
    """Each clip streamed once as the env streams it: latents (T, V, C, h, w) bf16, the first frame
    the first-frame model's (row i of the rollouts seeded ``tcfg.seed + i``). Computed on the main
    process, saved to the stage directory and loaded from there on resume (other ranks wait for the
    file)."""
    cache = run.stage_dir / ROLLOUTS_FILE
    if run.place.is_main and not cache.exists():
        student, scfg = run_student(run)
        device = run.place.device
        student = student.to(device).eval().requires_grad_(False)
        first_frames, how = run_first_frames(run, student, plain, scfg.streaming)
        windows = latent_windows(clips, plain, digest, run.run_dir, run.cfg, device)
        gen = torch.Generator().manual_seed(run.tcfg.seed)
        engine = StreamingEngine(student, scfg, lambda shape: torch.randn(tuple(shape), generator=gen).to(device))
        c = run.cfg.clip.chunk_frames
        out: list[torch.Tensor] = []
        batch = ROLLOUT_BATCH_CPU if device.type == "cpu" else len(clips)
        for g in range(0, len(clips), batch):
            rows = list(range(g, min(g + batch, len(clips))))
            cond = rollout_conditions(windows, rows, 0, 1, 0).to(device)
            first = first_frames.sample(cond, seed=[run.tcfg.seed + r for r in rows], **how)
            engine.start(first, cond)
            lengths = windows.lengths[rows]
            chunks = [first]
            for k in range(math.ceil((int(lengths.max()) - 1) / c)):
                chunks.append(engine.step(rollout_conditions(windows, rows, 1 + k * c, c, 0).to(device)))
            latents = torch.cat(chunks, dim=1).to(torch.bfloat16).cpu()
            out += [latents[j, : lengths[j]].clone() for j in range(len(rows))]
            progress = {"stage": f"{run.stage_dir.name}: rollouts", "clips_done": len(out), "clips": len(clips)}
            write_json_atomic(run.stage_dir / "progress.json", {**progress, "updated": time.strftime("%FT%T%z")})
        partial = cache.with_suffix(".partial")
        torch.save(out, partial)
        os.replace(partial, cache)
    run.place.barrier()
    return torch.load(cache, weights_only=True)


@dataclass
class RolloutData:
    """What a decoder learns from on the student's rollouts: the run's ``clips``, their
    ``sampler``, encoder ``latents`` (T, V, C, h, w) each, camera ``labels`` and LiDAR ``nearness``
    maps (:func:`decoder_maps`), and the ``rollouts`` (T, V, C, h, w) of the clips ``picked``
    (rollout r streams clip ``picked[r]``)."""

    clips: list[Clip]
    sampler: FrameSampler
    latents: list[torch.Tensor]
    labels: list[np.ndarray]
    nearness: list[np.ndarray] | None
    picked: list[int]
    rollouts: list[torch.Tensor]


def rollout_data(run: StageRun, cfg: ModelConfig, plain: SensorVAE, digest: str) -> RolloutData:
    """The run's :class:`RolloutData`: ``plain`` (the run's VAE, of :func:`encoder_digest`
    ``digest``) encodes the clips, the student rolls out :data:`ROLLOUT_CLIPS` of them."""
    clips = load_clips(run.data_dir, cfg)
    picked = rollout_clip_indices(len(clips))
    rollouts = student_rollouts(run, [clips[i] for i in picked], plain, digest)
    latents = run_latents(clips, plain, digest, run.run_dir, run.place.device)
    labels, nearness = decoder_maps(run, clips)
    return RolloutData(clips, FrameSampler(clips, cfg), latents, labels, nearness, picked, rollouts)


def rollout_targets(vae: SensorVAE, data: RolloutData) -> DecoderTargets:
    """What a decoder tuned on the rollouts learns to draw: the run's clips' frames, label and
    nearness maps, and their prompts' styles for ``vae``'s decoder."""
    return DecoderTargets(data.sampler, data.labels, data.nearness, clip_styles(vae, data.clips))


def rollout_batches(
    vae: SensorVAE, data: RolloutData, batch_size: int, views: int | None = None
) -> Callable[[Trainer], tuple[list[tuple[int, int, int]], torch.Tensor]]:
    """A decoder's batches: ``draw(trainer)`` gives ``batch_size`` (clip, frame, view) picks of the
    first ``views`` views (None: all, the LiDAR view too) and the latents (N, C, h, w) they are
    decoded from. :data:`ROLLOUT_SHARE` of them come from the rollouts, the rest are the
    encoder's latents with the decoder stage's jitter and drift."""
    sampler, latents, rollouts, picked = data.sampler, data.latents, data.rollouts, data.picked
    from_rollouts = round(batch_size * ROLLOUT_SHARE)
    rollout_views = sampler.cfg.sensors.num_views if views is None else views
    clip_lengths, rollout_lengths = [len(x) for x in latents], [len(x) for x in rollouts]

    def draw(tr: Trainer) -> tuple[list[tuple[int, int, int]], torch.Tensor]:
        own = sampler.pick(tr.rng, batch_size - from_rollouts, views)
        frames = decoded_frames(tr.rng, vae, own, clip_lengths)
        z = torch.stack([latents[c][g, v] for (c, _, v), g in zip(own, frames, strict=True)]).float()
        z = jittered_latents(tr, z, vae.draws_labels)
        rolled = []  # (rollout, frame, view)
        for r in tr.rng.integers(len(rollouts), size=from_rollouts).tolist():
            frame = int(tr.rng.integers(len(rollouts[r])))
            rolled.append((r, frame, int(tr.rng.integers(rollout_views))))
        frames = decoded_frames(tr.rng, vae, rolled, rollout_lengths)
        z_rolled = torch.stack([rollouts[r][g, v] for (r, _, v), g in zip(rolled, frames, strict=True)])
        picks = own + [(picked[r], f, v) for r, f, v in rolled]
        return picks, torch.cat([z, z_rolled.float().to(z.device)])

    return draw


def load_decoder_export(run_dir: Path, cfg: ModelConfig) -> SensorVAE:
    """The ``decoder`` stage's VAE, checked against ``cfg`` (sensors, VAE, layout)."""
    vae = load_vae(require_export(run_dir / "decoder" / EXPORT, "decoder"))
    if (vae.cfg.sensors, vae.cfg.vae, vae.cfg.layout) != (cfg.sensors, cfg.vae, cfg.layout):
        raise ValueError(
            f"{run_dir / 'decoder'} was trained with another preset or layout: train --stage decoder again "
            "with the same --preset and --layout"
        )
    return vae


def rollout_decoder_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/rollout_decoder`` (module docstring)."""
    cfg, tcfg = run.cfg, run.tcfg
    check_decoder_config(cfg)
    plain, digest = run_vae(run.run_dir, without_label_decoder(cfg), STAGE)
    vae = load_decoder_export(run.run_dir, cfg)
    data = rollout_data(run, cfg, plain, digest)
    torch.manual_seed(tcfg.seed)
    vae.train().requires_grad_(True)
    vae.encoder.requires_grad_(False)
    trainer = run.trainer(vae, STAGE)
    raster = LabelRasterizer()
    targets = rollout_targets(vae, data)
    # The LiDAR view too: the rollouts teach it to stand the returns where the scene's nearness map
    # says however the student's range latents lag.
    draw = rollout_batches(vae, data, tcfg.batch_size)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        picks, z = draw(tr)
        return decoder_loss(tr, vae, targets, picks, z)

    summary = trainer.run(step, STAGE)
    if not run.place.is_main:
        return summary
    metrics = export_decoder(run, STAGE, trainer, vae, plain, data.sampler, raster, targets.styles)
    return {**summary, "rollout_clips": len(data.rollouts), "metrics": metrics}
