"""Student stages (§4.2-§4.4): ``tf`` -> ``ode`` -> ``dmd`` -> ``long``, each into ``RUN/<stage>/``.

=======  ===========================================  ===================================================
stage    initialized from                              objective
=======  ===========================================  ===================================================
tf       RUN/teacher/model (bidirectional); with       rectified flow on a target chunk after clean GT
         ``dit.student_depth`` < ``depth``, evenly     history, block-causal attention
         spaced teacher blocks (student/init.py)
ode      RUN/tf/model (student); tf = ODE teacher      x0-regression at the 4 student times along the TF
                                                       model's guided Euler ODE (``sampler.steps``) to its
                                                       endpoint
dmd      RUN/ode/model; real score RUN/teacher/model   Self-Forcing rollouts with the streaming engine,
         critic initialized from the teacher (its      asymmetric DMD; ``critic_updates`` critic steps per
         depth, not the student's)                     generator step; p = ``denoise_loss_prob`` adds the
                                                       TF denoising loss on real latents
long     RUN/dmd/model (+ RUN/dmd/critic)              one self-rollout of ``long_frames`` frames continued
                                                       across steps; each step DMD-trains the newly
                                                       generated clip with earlier frames as detached
                                                       cached context (LongLive); the same p adds the TF
                                                       denoising loss on a real window;
                                                       ``long_skip_chunks`` untrained chunks between
                                                       trained clips reach late frames in fewer steps
steps    RUN/long/model (+ RUN/long/critic); real      long's objective with the student streaming at
         score RUN/teacher/model                       fewer denoising steps (``denoising_steps``, by
                                                       default half the long student's): a faster env
=======  ===========================================  ===================================================

Every stage uses the shared :class:`Trainer` (atomic checkpoints, resume, EMA export, NaN guard);
``dmd``/``long`` train one module holding generator and critic, so both and their optimizer
state are checkpointed together. Under ``torchrun`` each rank rolls out its shard of the global
batch, drawing its noise as its rows of the global batch's (:meth:`Trainer.shard`), and both the
critic's and the generator's gradients are averaged over the ranks before their updates.
A resumed ``long`` or ``steps`` run starts a fresh self-rollout. A run started from a bundle
(:func:`world_model.train.seed_run.seed_run`) has the bundle's student as ``RUN/long`` and its
reference model, cut to the teacher's input, as ``RUN/teacher``: the ``steps`` stage then teaches the
shipped student fewer steps with no training run at hand.
Long rollouts need controls for ``long_frames`` frames: clips shorter than that are played
back and forth (reflected), which keeps consecutive frames physically adjacent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import torch
from torch import nn

from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import predict_x0, sample_timesteps
from world_model.student.config import StudentConfig
from world_model.student.engine import StreamingEngine
from world_model.student.init import student_from_teacher
from world_model.student.losses import ode_regression_loss
from world_model.student.training import (
    critic_flow_loss,
    dmd_generator_loss,
    dmd_times,
    ode_targets,
    real_score_guidance,
    self_forcing_rollout,
    teacher_forcing_loss,
    teacher_forcing_velocity,
)
from world_model.train.checkpoint import export_weights
from world_model.train.data import LatentWindows
from world_model.train.exports import CRITIC, EXPORT, export_student_config, load_teacher, require_export
from world_model.train.rollouts import rollout_conditions, rollout_starts
from world_model.train.run import StageOptions, StageRun
from world_model.train.trainer import Trainer, TrainingDivergedError

PREDECESSOR = {"tf": "teacher", "ode": "tf", "dmd": "ode", "long": "dmd", "steps": "long"}
# A resumed student stage must stream at the denoising steps its checkpoint was trained at.
RESUME_KEYS = {"denoising_steps": StudentConfig().num_steps}


class _Pair(nn.Module):
    """Generator + critic trained by one Trainer (one optimizer; each update touches one of them)."""

    def __init__(self, generator: MultiViewDiT, critic: MultiViewDiT) -> None:
        super().__init__()
        self.generator, self.critic = generator, critic


def _load_same(path: Path, stage: str, cfg: ModelConfig) -> MultiViewDiT:
    """The export at ``path`` (of ``stage``), checked against ``cfg``: a student without the decoder's
    settings (it never reads the label maps or the range head: a bundle's student has its decoder's);
    the teacher (and the critic, its copy) under :meth:`ModelConfig.teacher_settings`."""
    model = load_teacher(require_export(path, stage))
    if stage == "teacher":
        same = model.cfg.teacher_settings() == cfg.teacher_settings()
    else:
        same = without_label_decoder(model.cfg) == without_label_decoder(cfg)
    if not same:
        raise ValueError(f"{path} was trained with preset {model.cfg.name!r} / another config; use the same preset")
    return model


def _frozen(model: MultiViewDiT, device: torch.device) -> MultiViewDiT:
    return model.to(device).eval().requires_grad_(False)


def _max_chunks(windows: LatentWindows, cfg: ModelConfig, scfg: StudentConfig) -> int:
    """Most chunks after the prefix that fit both the teacher's clip lengths and the data."""
    longest = min(max(cfg.clip.train_frames), int(windows.lengths.max()))
    k = (longest - scfg.prefix_frames) // cfg.clip.chunk_frames
    if k < 1:
        raise ValueError(
            f"clips of {longest} frames cannot hold {scfg.prefix_frames} prefix frames + one chunk of "
            f"{cfg.clip.chunk_frames}; record longer clips"
        )
    return k


def _row_noise(tr: Trainer):  # noqa: ANN202 - the engine's NoiseSource
    """The engine's noise: this rank's rows of noise drawn for the global batch."""
    world = tr.place.world_size
    return lambda shape: tr.shard(tr.randn(shape[0] * world, *shape[1:]))


def _trainer(run: StageRun, model: nn.Module, stage: str, scfg: StudentConfig) -> Trainer:
    """The stage's trainer; a resume must keep the denoising steps (:data:`RESUME_KEYS`)."""
    return run.trainer(model, stage, RESUME_KEYS, denoising_steps=scfg.num_steps)


def _export(stage_dir: Path, trainer: Trainer, state: dict, cfg: ModelConfig, scfg: StudentConfig, stage: str) -> None:
    meta = {"stage": stage, "step": trainer.step, "model_config": cfg.to_dict(), "student_config": scfg.to_dict()}
    export_weights(stage_dir / EXPORT, state, meta)


# -- tf / ode ------------------------------------------------------------------------------------


def _tf_stage(run: StageRun, windows: LatentWindows, scfg: StudentConfig) -> dict:
    cfg, tcfg = run.cfg, run.tcfg
    teacher = _load_same(run.run_dir / "teacher" / EXPORT, "teacher", cfg)
    model = student_from_teacher(teacher, cfg.for_student()).train().requires_grad_(True)
    del teacher
    trainer = _trainer(run, model, "tf", scfg)
    c, kmax = cfg.clip.chunk_frames, _max_chunks(windows, cfg, scfg)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        frames = scfg.prefix_frames + c * int(tr.rng.integers(1, kmax + 1))
        x0, cond = windows.sample(tr.rng, tcfg.batch_size, frames)
        b = x0.shape[0]
        drop = tr.rand(b) < cfg.flow.cond_drop_prob  # keeps CFG usable
        t = sample_timesteps((b,), cfg.flow, tr.gen)
        noise = tr.randn(b, *cfg.latent_shape(c))
        x0, cond, t, noise = tr.shard(x0), tr.shard(cond).with_drop(tr.shard(drop)), tr.shard(t), tr.shard(noise)
        return teacher_forcing_loss(model, x0, cond, t, noise, scfg.prefix_frames), x0.shape[0]

    summary = trainer.run(step, "tf")
    if run.place.is_main:
        _export(run.stage_dir, trainer, trainer.ema.model_state(model), model.cfg, scfg, "tf")
    return summary


def _ode_stage(run: StageRun, windows: LatentWindows, scfg: StudentConfig) -> dict:
    cfg, tcfg = run.cfg, run.tcfg
    tf_path = run.run_dir / "tf" / EXPORT
    ode_teacher = _frozen(_load_same(tf_path, "tf", cfg.for_student()), run.device)
    student = _load_same(tf_path, "tf", cfg.for_student()).train().requires_grad_(True)
    trainer = _trainer(run, student, "ode", scfg)
    c, kmax, times = cfg.clip.chunk_frames, _max_chunks(windows, cfg, scfg), scfg.times().to(run.device)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        frames = scfg.prefix_frames + c * int(tr.rng.integers(1, kmax + 1))
        x0, cond = windows.sample(tr.rng, tcfg.batch_size, frames)
        b = x0.shape[0]
        noise, k = tr.shard(tr.randn(b, *cfg.latent_shape(c))), tr.shard(tr.randint(len(times), b))
        x0, cond = tr.shard(x0), tr.shard(cond)
        history, rows = x0[:, :-c], torch.arange(x0.shape[0], device=x0.device)
        points, end = ode_targets(ode_teacher, history, cond, noise, scfg)
        xt, t = points[k, rows], times[k]
        v = teacher_forcing_velocity(student, history, xt, t, cond, scfg.prefix_frames)
        return ode_regression_loss(predict_x0(xt, v, t), end), x0.shape[0]

    summary = trainer.run(step, "ode")
    if run.place.is_main:
        _export(run.stage_dir, trainer, trainer.ema.model_state(student), student.cfg, scfg, "ode")
    return summary


# -- dmd / long ----------------------------------------------------------------------------------


def _critic_update(tr: Trainer, pair: _Pair, video: torch.Tensor, cond: Conditions, global_batch: int) -> float:
    """One critic step on a detached student clip (this rank's rows); raises when its loss diverges."""
    cfg = pair.critic.cfg
    t = tr.shard(sample_timesteps((global_batch,), cfg.flow, tr.gen))
    noise = tr.shard(tr.randn(global_batch, *video.shape[1:]))
    loss = critic_flow_loss(pair.critic, video, cond, t, noise)
    value = tr.place.mean(float(loss.detach()))
    if not math.isfinite(value):
        raise TrainingDivergedError(
            f"critic loss is {value} at step {tr.step + 1}; the last good checkpoint (if any) is kept in "
            f"{tr.ckpt_dir}. Lower the learning rate, then rerun the same command to resume."
        )
    tr.opt.zero_grad(set_to_none=True)  # only the critic gets gradients: the step leaves the generator alone
    loss.backward()
    tr.place.average_gradients(pair.critic)
    if tr.tcfg.grad_clip > 0:
        nn.utils.clip_grad_norm_(pair.critic.parameters(), tr.tcfg.grad_clip)
    tr.opt.step()
    return value


def _pair(run: StageRun, init_stage: str) -> tuple[_Pair, MultiViewDiT]:
    run_dir, cfg = run.run_dir, run.cfg
    real = _frozen(_load_same(run_dir / "teacher" / EXPORT, "teacher", cfg), run.device)
    generator = _load_same(run_dir / init_stage / EXPORT, init_stage, cfg.for_student())
    critic_path = run_dir / init_stage / CRITIC
    source = critic_path if critic_path.with_suffix(".safetensors").exists() else run_dir / "teacher" / EXPORT
    critic = _load_same(source, "teacher", cfg)
    return _Pair(generator.train().requires_grad_(True), critic.train().requires_grad_(True)), real


def _export_pair(stage_dir: Path, trainer: Trainer, pair: _Pair, scfg: StudentConfig, stage: str) -> None:
    ema = trainer.ema.model_state(pair)
    gen = {k.removeprefix("generator."): v for k, v in ema.items() if k.startswith("generator.")}
    _export(stage_dir, trainer, gen, pair.generator.cfg, scfg, stage)
    meta = {"stage": stage, "step": trainer.step, "model_config": pair.critic.cfg.to_dict(), "role": "critic"}
    export_weights(stage_dir / CRITIC, pair.critic.state_dict(), meta)


def _denoising_loss(
    tr: Trainer, model: MultiViewDiT, x0: torch.Tensor, cond: Conditions, scfg: StudentConfig
) -> torch.Tensor:
    """The supervised denoising term on real latents that the dmd and long stages add with probability
    ``scfg.denoise_loss_prob``: the last chunk of ``x0`` (the global batch) at one of the student's own
    times, under its clean history. It keeps the few-step generator anchored to the data while DMD
    only sees its samples."""
    b, c = x0.shape[0], model.cfg.clip.chunk_frames
    times = scfg.times().to(tr.place.device)
    t = tr.shard(times[tr.randint(len(times), b)])
    noise = tr.shard(tr.randn(b, *model.cfg.latent_shape(c)))
    return teacher_forcing_loss(model, tr.shard(x0), tr.shard(cond), t, noise, scfg.prefix_frames)


def _dmd_stage(run: StageRun, windows: LatentWindows, scfg: StudentConfig) -> dict:
    cfg, tcfg = run.cfg, run.tcfg
    pair, real = _pair(run, "ode")
    guidance = real_score_guidance(real, scfg)
    trainer = _trainer(run, pair, "dmd", scfg)
    c, p = cfg.clip.chunk_frames, scfg.prefix_frames
    chunks = _max_chunks(windows, cfg, scfg)
    engine = StreamingEngine(pair.generator, scfg, _row_noise(trainer))

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        x0_all, cond_all = windows.sample(tr.rng, tcfg.batch_size, p + chunks * c)
        x0, cond = tr.shard(x0_all), tr.shard(cond_all)
        for _ in range(scfg.critic_updates):
            with torch.no_grad():
                fake = self_forcing_rollout(engine, x0[:, :p], cond, chunks, None, grad=False)
            _critic_update(tr, pair, fake, cond, tcfg.batch_size)
        exit_step = int(tr.randint(scfg.num_steps, 1))
        video = self_forcing_rollout(engine, x0[:, :p], cond, chunks, exit_step, grad=True)
        t = tr.shard(dmd_times(tcfg.batch_size, scfg, tr.gen))
        noise = tr.shard(tr.randn(tcfg.batch_size, *video.shape[1:]))
        loss = dmd_generator_loss(real, pair.critic, video, cond, t, noise, p, guidance)
        if tr.rng.random() < scfg.denoise_loss_prob:
            loss = loss + _denoising_loss(tr, pair.generator, x0_all, cond_all, scfg)
        return loss, video.shape[0]

    summary = trainer.run(step, "dmd")
    if run.place.is_main:
        _export_pair(run.stage_dir, trainer, pair, scfg, "dmd")
    return summary


def _long_stage(run: StageRun, windows: LatentWindows, scfg: StudentConfig, stage: str = "long") -> dict:
    """LongLive's continuing self-rollout (``long``), or the same from the long student at fewer
    denoising steps (``steps``)."""
    cfg, tcfg = run.cfg, run.tcfg
    pair, real = _pair(run, PREDECESSOR[stage])
    guidance = real_score_guidance(real, scfg)
    trainer = _trainer(run, pair, stage, scfg)
    c, p = cfg.clip.chunk_frames, scfg.prefix_frames
    clip_frames = scfg.long_clip_chunks * c
    skip_frames = scfg.long_skip_chunks * c
    real_frames = p + _max_chunks(windows, cfg, scfg) * c  # the real windows of the denoising term
    engine = StreamingEngine(pair.generator, scfg, _row_noise(trainer))
    state: dict = {"clips": None}  # the global batch's clips; this rank rolls out its rows

    def conditions(start: int, frames: int, anchor: int) -> Conditions:
        return trainer.shard(rollout_conditions(windows, state["clips"], start, frames, anchor))

    def start(tr: Trainer) -> None:
        clips, first, cond = rollout_starts(windows, tr.rng, tcfg.batch_size, p)
        engine.start(tr.shard(first), tr.shard(cond))
        state["clips"] = clips

    def generate(cond: Conditions, grad: bool, exit_step: int | None) -> torch.Tensor:
        return torch.cat(
            [
                engine.step(cond.frames(k * c, (k + 1) * c), exit_step=exit_step, grad=grad)
                for k in range(scfg.long_clip_chunks)
            ],
            dim=1,
        )

    def advance() -> None:
        """``long_skip_chunks`` untrained chunks between two trained clips (see StudentConfig)."""
        with torch.no_grad():
            for _ in range(scfg.long_skip_chunks):
                engine.step(conditions(engine.position, c, 0))

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        fresh = state["clips"] is None or engine.position + skip_frames + clip_frames > scfg.long_frames
        if fresh:
            start(tr)  # and trains the new rollout's first clip at once
        else:
            advance()
        pos = engine.position
        controls = conditions(pos, clip_frames, 0)  # the rollout's own frame
        scored = conditions(pos, clip_frames, pos)  # the teacher sees the clip alone
        for _ in range(scfg.critic_updates):
            snap = engine.snapshot()  # extra samples from the same context, then rewind
            with torch.no_grad():
                fake = generate(controls, False, None)
            engine.restore(snap)
            _critic_update(tr, pair, fake, scored, tcfg.batch_size)
        clip = generate(controls, True, int(tr.randint(scfg.num_steps, 1)))
        t = tr.shard(dmd_times(tcfg.batch_size, scfg, tr.gen))
        noise = tr.shard(tr.randn(tcfg.batch_size, *clip.shape[1:]))
        loss = dmd_generator_loss(real, pair.critic, clip, scored, t, noise, guidance=guidance)
        if tr.rng.random() < scfg.denoise_loss_prob:
            x0, cond = windows.sample(tr.rng, tcfg.batch_size, real_frames)
            loss = loss + _denoising_loss(tr, pair.generator, x0, cond, scfg)
        return loss, clip.shape[0] * clip_frames

    summary = trainer.run(step, stage)
    if run.place.is_main:
        _export_pair(run.stage_dir, trainer, pair, scfg, stage)
    return {**summary, "rollout_frames": engine.position}


STUDENT_STAGE_FNS = {
    "tf": _tf_stage,
    "ode": _ode_stage,
    "dmd": _dmd_stage,
    "long": _long_stage,
    "steps": partial(_long_stage, stage="steps"),
}


@dataclass(frozen=True, kw_only=True)
class StudentStageOptions(StageOptions):
    """The student stages' options: :class:`StageOptions` and the student's config."""

    student: StudentConfig = field(default_factory=StudentConfig)
    # The denoising steps the student streams at while trained (None: the student config's; for the
    # ``steps`` stage half its predecessor's, at least one).
    denoising_steps: int | None = None


def student_setup(options: StudentStageOptions) -> dict:
    """The keyword arguments of :func:`student_stage` from the stage's options."""
    return {"scfg": options.student, "denoising_steps": options.denoising_steps}


def taught_steps(scfg: StudentConfig, denoising_steps: int | None, stage: str, predecessor: Path) -> StudentConfig:
    """``scfg`` streaming at the stage's denoising steps (:class:`StudentStageOptions`); the ``steps``
    stage refuses as many steps as its predecessor's or more."""
    before = export_student_config(predecessor).num_steps if stage == "steps" else None
    if denoising_steps is None:
        denoising_steps = scfg.num_steps if before is None else max(1, before // 2)
    if before is not None and denoising_steps >= before:
        raise ValueError(
            f"the steps stage teaches fewer denoising steps than {predecessor}'s {before}, not {denoising_steps}: "
            f"give --denoising-steps below {before}"
        )
    return replace(scfg, streaming=replace(scfg.streaming, denoising_steps=denoising_steps))


def student_stage(stage: str, run: StageRun, scfg: StudentConfig, denoising_steps: int | None = None) -> dict:
    """Train (or resume) student stage ``stage`` (tf, ode, dmd, long, steps) of ``run`` with the
    student config ``scfg`` at ``denoising_steps`` (:func:`taught_steps`; module docstring)."""
    predecessor = require_export(run.run_dir / PREDECESSOR[stage] / EXPORT, PREDECESSOR[stage])
    scfg = taught_steps(scfg, denoising_steps, stage, predecessor)
    windows = run.latents(stage)
    torch.manual_seed(run.tcfg.seed)
    return STUDENT_STAGE_FNS[stage](run, windows, scfg)
