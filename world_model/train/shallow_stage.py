"""The ``shallow`` stage: the run's finished student distilled into fewer blocks, a cheaper env step.

    python -m world_model.train.recipe --out RUN --scale cpu --from-bundle BUNDLE --phases shallow --episodes 4
    python -m world_model.train --stage shallow --student-depth 5 --data DATA --run RUN

Each block of the student runs twice an env step (the chunk's denoising pass and its cache write),
so its depth sets most of a world-model step's time. The run's student (``RUN/steps``, else
``RUN/long``: a taught or a seeded bundle's) and a copy of it keeping ``dit.student_depth`` evenly
spaced blocks (:func:`~world_model.student.init.student_from_teacher`) stream the run's clips side
by side as the env would (:func:`~world_model.streaming.taught_streaming`): the same controls, the same noise, each
its own KV cache of the same context. Per chunk the shallow student's latents regress onto the deep
one's (:func:`mimic_loss`), and the chunk then enters both caches: the shallow student's own with
probability :data:`OWN_CONTEXT_SHARE`, so that it learns from the contexts it makes itself, else the
deep one's. A rollout runs :data:`ROLLOUT_CHUNKS` chunks, then starts again on other clips.

Mimicking the deep student, not learning the data anew, keeps the rest of a bundle valid: the VAE's
decoders and range head were tuned on the deep student's rollouts and draw the shallow one's as they
draw those (the first frames are the first-frame model's, untouched). The recipe's ``tf`` ... ``steps``
chain run at fewer blocks ranked the policy zoo worse (docs/experiments.md).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from world_model.model.config import ModelConfig, with_student_settings
from world_model.model.dit import MultiViewDiT
from world_model.streaming import taught_streaming
from world_model.student.config import StudentConfig
from world_model.student.engine import StreamingEngine
from world_model.student.init import student_from_teacher
from world_model.train.checkpoint import export_weights
from world_model.train.exports import EXPORT, load_student
from world_model.train.rollouts import rollout_conditions, rollout_starts
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer

STAGE = "shallow"
DEEP_STAGES = ("steps", "long")  # the student distilled: the first that has an export
ROLLOUT_CHUNKS = 30  # chunks of a lockstep rollout before it starts again on other clips
OWN_CONTEXT_SHARE = 0.5  # of the chunks committed: the shallow student's own, the rest the deep one's


def mimic_loss(shallow: torch.Tensor, deep: torch.Tensor) -> torch.Tensor:
    """Mean squared error of the shallow student's chunk latents (B, chunk, V, C, h, w) to the deep
    one's for the same context and noise (float32, whatever precision produced them)."""
    if shallow.shape != deep.shape:
        raise ValueError(f"latents differ in shape: {tuple(shallow.shape)} and {tuple(deep.shape)}")
    return ((shallow.float() - deep.float()) ** 2).mean()


def deep_student(run_dir: Path) -> tuple[MultiViewDiT, StudentConfig, str]:
    """The run's student to distil (:data:`DEEP_STAGES`), its student config streaming as a bundle
    exported from the run streams it (:func:`~world_model.streaming.taught_streaming`), and its stage."""
    for stage in DEEP_STAGES:
        path = run_dir / stage / EXPORT
        if path.with_suffix(".safetensors").exists():
            model, scfg = load_student(path)
            return model, replace(scfg, streaming=taught_streaming(scfg.num_steps)), stage
    raise FileNotFoundError(
        f"--stage {STAGE} distils the run's finished student: train --stage {DEEP_STAGES[-1]} (or seed the run "
        f"from a bundle, the recipe's --from-bundle) with the same --run first"
    )


def shallow_config(cfg: ModelConfig, deep: ModelConfig) -> ModelConfig:
    """The shallow student's config: ``cfg``'s ``dit.student_depth`` blocks, fewer than the deep one's."""
    depth = cfg.dit.student_depth
    if depth is None or depth >= deep.dit.depth:
        raise ValueError(
            f"--stage {STAGE} keeps fewer blocks than the run's student's {deep.dit.depth}: give --student-depth "
            f"below {deep.dit.depth} (dit.student_depth), got {depth}"
        )
    return with_student_settings(deep, depth)


def shallow_stage(run: StageRun) -> dict:
    """Train (or resume) the ``shallow`` stage of ``run`` (module docstring)."""
    deep, scfg, deep_stage = deep_student(run.run_dir)
    shallow = student_from_teacher(deep, shallow_config(run.cfg, deep.cfg)).train().requires_grad_(True)
    deep = deep.to(run.device).eval().requires_grad_(False)
    windows = run.latents(STAGE)
    trainer = run.trainer(shallow, STAGE, model_config=shallow.cfg.to_dict(), distilled_from=deep_stage)
    c, batch = run.cfg.clip.chunk_frames, run.tcfg.batch_size
    noise: dict[str, torch.Tensor] = {}
    engines = [StreamingEngine(model, scfg, lambda shape: noise["chunk"]) for model in (deep, shallow)]
    state = {"clips": None, "chunks": ROLLOUT_CHUNKS}

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        if state["chunks"] >= ROLLOUT_CHUNKS:
            clips, first, cond = rollout_starts(windows, tr.rng, batch, scfg.prefix_frames)
            with torch.no_grad():
                for engine in engines:
                    engine.start(tr.shard(first), tr.shard(cond))
            state["clips"], state["chunks"] = clips, 0
        controls = tr.shard(rollout_conditions(windows, state["clips"], engines[0].position, c, 0))
        noise["chunk"] = tr.shard(tr.randn(batch, *run.cfg.latent_shape(c)))
        with torch.no_grad():
            target, deep_tokens = engines[0].denoise(controls)
        latents, tokens = engines[1].denoise(controls, grad=True)
        context = latents.detach() if tr.rng.random() < OWN_CONTEXT_SHARE else target
        with torch.no_grad():
            engines[0].commit(context, controls, deep_tokens)
            engines[1].commit(context, controls, tokens)
        state["chunks"] += 1
        return mimic_loss(latents, target), latents.shape[0] * c

    summary = trainer.run(step, STAGE)
    if run.place.is_main:
        meta = {
            "stage": STAGE,
            "step": trainer.step,
            "model_config": shallow.cfg.to_dict(),
            "student_config": scfg.to_dict(),
            "distilled_from": deep_stage,
        }
        export_weights(run.stage_dir / EXPORT, trainer.ema.model_state(shallow), meta)
    return summary
