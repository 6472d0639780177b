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
=======  ===========================================  ===================================================

Every stage uses the shared :class:`Trainer` (atomic checkpoints, resume, EMA export, NaN guard);
``dmd``/``long`` train one module holding generator and critic, so both and their optimizer
state are checkpointed together. A resumed ``long`` run starts a fresh self-rollout.
Long rollouts need controls for ``long_frames`` frames: clips shorter than that are played
back and forth (reflected), which keeps consecutive frames physically adjacent.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import predict_x0, sample_timesteps
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.text import make_text_encoder
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
from world_model.train.data import LatentWindows, cached_latents, file_digest, latent_cache_dir, load_clips
from world_model.train.stages import EXPORT, load_teacher, load_vae
from world_model.train.trainer import TrainConfig, Trainer, TrainingDivergedError

STUDENT_STAGES = ("tf", "ode", "dmd", "long", "compress")  # compress: compress_stage.py
PREDECESSOR = {"tf": "teacher", "ode": "tf", "dmd": "ode", "long": "dmd"}
CRITIC = "critic"  # RUN/dmd/critic.safetensors + critic.json


@dataclass(frozen=True)
class StageRun:
    """What a student stage works with: its data, the run's folders and its configs."""

    windows: LatentWindows
    run_dir: Path  # RUN/: the earlier stages' exports
    stage_dir: Path  # RUN/<stage>/: this stage's checkpoints and export
    cfg: ModelConfig
    scfg: StudentConfig
    tcfg: TrainConfig
    progress: bool

    def trainer(self, model: nn.Module, stage: str, **meta: object) -> Trainer:
        """The stage's :class:`Trainer` (checkpoints in ``stage_dir``, metadata naming the stage)."""
        info = {"stage": stage, "model_config": self.cfg.to_dict(), **meta}
        return Trainer(self.stage_dir, model, self.tcfg, info, self.progress)


def load_student(path: str | Path) -> tuple[MultiViewDiT, StudentConfig]:
    """A student exported by ``tf``/``ode``/``dmd``/``long``, with its :class:`StudentConfig`."""
    path = Path(path).with_suffix("")
    meta = json.loads(path.with_suffix(".json").read_text())
    return load_teacher(path), StudentConfig.from_dict(meta.get("student_config", {}))


class _Pair(nn.Module):
    """Generator + critic trained by one Trainer (one optimizer; each update touches one of them)."""

    def __init__(self, generator: MultiViewDiT, critic: MultiViewDiT) -> None:
        super().__init__()
        self.generator, self.critic = generator, critic


def _need(path: Path, stage: str) -> Path:
    if not path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(f"{path}.safetensors is missing; run --stage {stage} with the same --run first")
    return path


def _load_same(path: Path, stage: str, cfg: ModelConfig) -> MultiViewDiT:
    """The export at ``path`` (of ``stage``), checked against ``cfg``: exactly for a student;
    under :meth:`ModelConfig.teacher_settings` for the teacher (and the critic, its copy)."""
    model = load_teacher(_need(path, stage))
    same = model.cfg.teacher_settings() == cfg.teacher_settings() if stage == "teacher" else model.cfg == cfg
    if not same:
        raise ValueError(f"{path} was trained with preset {model.cfg.name!r} / another config; use the same preset")
    return model


def _frozen(model: MultiViewDiT) -> MultiViewDiT:
    return model.eval().requires_grad_(False)


def _windows(data_dir: Path, run_dir: Path, cfg: ModelConfig) -> LatentWindows:
    vae_path = _need(run_dir / "vae" / EXPORT, "vae")
    vae = load_vae(vae_path)
    clips = load_clips(data_dir, cfg)
    digest = file_digest(vae_path.with_suffix(".safetensors"))
    latents = [cached_latents(c, vae, latent_cache_dir(run_dir), digest) for c in clips]
    return LatentWindows(clips, latents, cfg, make_text_encoder(cfg.text), VaeCropEncoder(vae))


def _max_chunks(windows: LatentWindows, cfg: ModelConfig, scfg: StudentConfig) -> int:
    """Most chunks after the prefix that fit both the teacher's clip lengths and the data."""
    longest = min(max(cfg.clip.train_frames), max(c.num_frames for c in windows.clips))
    k = (longest - scfg.prefix_frames) // cfg.clip.chunk_frames
    if k < 1:
        raise ValueError(
            f"clips of {longest} frames cannot hold {scfg.prefix_frames} prefix frames + one chunk of "
            f"{cfg.clip.chunk_frames}; record longer clips"
        )
    return k


def _sample(
    windows: LatentWindows, rng: np.random.Generator, batch: int, frames: int
) -> tuple[torch.Tensor, Conditions]:
    """x0 (B, frames, ...) and conditions of random windows (ego relative to each window's start)."""
    lengths = [c.num_frames for c in windows.clips]
    eligible = [i for i, n in enumerate(lengths) if n >= frames]
    picks = rng.choice(eligible, size=batch)
    items = [windows.window(int(ci), int(rng.integers(lengths[ci] - frames + 1)), frames) for ci in picks]
    return torch.stack([x for x, _ in items]).float(), Conditions.collate([a for _, a in items])


def _noise(shape: tuple[int, ...], tr: Trainer) -> torch.Tensor:
    return torch.randn(shape, generator=tr.gen)


def _export(stage_dir: Path, trainer: Trainer, state: dict, cfg: ModelConfig, scfg: StudentConfig, stage: str) -> None:
    meta = {"stage": stage, "step": trainer.step, "model_config": cfg.to_dict(), "student_config": scfg.to_dict()}
    export_weights(stage_dir / EXPORT, state, meta)


# -- tf / ode ------------------------------------------------------------------------------------


def _tf_stage(run: StageRun) -> dict:
    windows, run_dir, stage_dir = run.windows, run.run_dir, run.stage_dir
    cfg, scfg, tcfg = run.cfg, run.scfg, run.tcfg
    teacher = _load_same(run_dir / "teacher" / EXPORT, "teacher", cfg)
    model = student_from_teacher(teacher, cfg.for_student()).train().requires_grad_(True)
    del teacher
    trainer = run.trainer(model, "tf")
    c, kmax = cfg.clip.chunk_frames, _max_chunks(windows, cfg, scfg)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        frames = scfg.prefix_frames + c * int(tr.rng.integers(1, kmax + 1))
        x0, cond = _sample(windows, tr.rng, tcfg.batch_size, frames)
        b = x0.shape[0]
        cond = cond.with_drop(torch.rand(b, generator=tr.gen) < cfg.flow.cond_drop_prob)  # keeps CFG usable
        t = sample_timesteps((b,), cfg.flow, tr.gen)
        return teacher_forcing_loss(model, x0, cond, t, _noise((b, *cfg.latent_shape(c)), tr), scfg.prefix_frames), b

    summary = trainer.run(step, "tf")
    _export(stage_dir, trainer, trainer.ema.model_state(model), model.cfg, scfg, "tf")
    return summary


def _ode_stage(run: StageRun) -> dict:
    windows, run_dir, stage_dir = run.windows, run.run_dir, run.stage_dir
    cfg, scfg, tcfg = run.cfg, run.scfg, run.tcfg
    tf_path = run_dir / "tf" / EXPORT
    ode_teacher = _frozen(_load_same(tf_path, "tf", cfg.for_student()))
    student = _load_same(tf_path, "tf", cfg.for_student()).train().requires_grad_(True)
    trainer = run.trainer(student, "ode")
    c, kmax, times = cfg.clip.chunk_frames, _max_chunks(windows, cfg, scfg), scfg.times()

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        frames = scfg.prefix_frames + c * int(tr.rng.integers(1, kmax + 1))
        x0, cond = _sample(windows, tr.rng, tcfg.batch_size, frames)
        b, history = x0.shape[0], x0[:, :-c]
        points, end = ode_targets(ode_teacher, history, cond, _noise((b, *cfg.latent_shape(c)), tr), scfg)
        k = torch.randint(len(times), (b,), generator=tr.gen)
        xt, t = points[k, torch.arange(b)], times[k]
        v = teacher_forcing_velocity(student, history, xt, t, cond, scfg.prefix_frames)
        return ode_regression_loss(predict_x0(xt, v, t), end), b

    summary = trainer.run(step, "ode")
    _export(stage_dir, trainer, trainer.ema.model_state(student), student.cfg, scfg, "ode")
    return summary


# -- dmd / long ----------------------------------------------------------------------------------


def _critic_update(tr: Trainer, pair: _Pair, video: torch.Tensor, cond: Conditions, cfg: ModelConfig) -> float:
    """One critic step on a detached student clip; raises when its loss diverges."""
    b = video.shape[0]
    loss = critic_flow_loss(pair.critic, video, cond, sample_timesteps((b,), cfg.flow, tr.gen), _noise(video.shape, tr))
    value = float(loss.detach())
    if not math.isfinite(value):
        raise TrainingDivergedError(
            f"critic loss is {value} at step {tr.step + 1}; the last good checkpoint (if any) is kept in "
            f"{tr.ckpt_dir}. Lower the learning rate, then rerun the same command to resume."
        )
    tr.opt.zero_grad(set_to_none=True)  # only the critic gets gradients: the step leaves the generator alone
    loss.backward()
    if tr.tcfg.grad_clip > 0:
        nn.utils.clip_grad_norm_(pair.critic.parameters(), tr.tcfg.grad_clip)
    tr.opt.step()
    return value


def _pair(run_dir: Path, init_stage: str, cfg: ModelConfig) -> tuple[_Pair, MultiViewDiT]:
    real = _frozen(_load_same(run_dir / "teacher" / EXPORT, "teacher", cfg))
    generator = _load_same(run_dir / init_stage / EXPORT, init_stage, cfg.for_student())
    critic_path = run_dir / init_stage / CRITIC
    source = critic_path if critic_path.with_suffix(".safetensors").exists() else run_dir / "teacher" / EXPORT
    critic = _load_same(source, "teacher", cfg)
    return _Pair(generator.train().requires_grad_(True), critic.train().requires_grad_(True)), real


def _export_pair(
    stage_dir: Path, trainer: Trainer, pair: _Pair, cfg: ModelConfig, scfg: StudentConfig, stage: str
) -> None:
    ema = trainer.ema.model_state(pair)
    gen = {k.removeprefix("generator."): v for k, v in ema.items() if k.startswith("generator.")}
    _export(stage_dir, trainer, gen, pair.generator.cfg, scfg, stage)
    meta = {"stage": stage, "step": trainer.step, "model_config": pair.critic.cfg.to_dict(), "role": "critic"}
    export_weights(stage_dir / CRITIC, pair.critic.state_dict(), meta)


def _denoising_loss(
    tr: Trainer, model: MultiViewDiT, x0: torch.Tensor, cond: Conditions, scfg: StudentConfig
) -> torch.Tensor:
    """The supervised denoising term on real latents that the dmd and long stages add with probability
    ``scfg.denoise_loss_prob``: the last chunk of ``x0`` at one of the student's own times, under its
    clean history. It keeps the few-step generator anchored to the data while DMD only sees its samples."""
    b, c = x0.shape[0], model.cfg.clip.chunk_frames
    times = scfg.times()
    t = times[torch.randint(len(times), (b,), generator=tr.gen)]
    return teacher_forcing_loss(model, x0, cond, t, _noise((b, *model.cfg.latent_shape(c)), tr), scfg.prefix_frames)


def _dmd_stage(run: StageRun) -> dict:
    windows, run_dir, stage_dir = run.windows, run.run_dir, run.stage_dir
    cfg, scfg, tcfg = run.cfg, run.scfg, run.tcfg
    pair, real = _pair(run_dir, "ode", cfg)
    guidance = real_score_guidance(real, scfg)
    trainer = run.trainer(pair, "dmd")
    c, p = cfg.clip.chunk_frames, scfg.prefix_frames
    chunks = _max_chunks(windows, cfg, scfg)
    engine = StreamingEngine(pair.generator, scfg, trainer.gen)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        x0, cond = _sample(windows, tr.rng, tcfg.batch_size, p + chunks * c)
        for _ in range(scfg.critic_updates):
            with torch.no_grad():
                fake = self_forcing_rollout(engine, x0[:, :p], cond, chunks, None, grad=False)
            _critic_update(tr, pair, fake, cond, cfg)
        exit_step = int(torch.randint(scfg.num_steps, (1,), generator=tr.gen))
        video = self_forcing_rollout(engine, x0[:, :p], cond, chunks, exit_step, grad=True)
        b = video.shape[0]
        t, noise = dmd_times(b, scfg, tr.gen), _noise(video.shape, tr)
        loss = dmd_generator_loss(real, pair.critic, video, cond, t, noise, p, guidance, dmd_norm=scfg.dmd_norm)
        if tr.rng.random() < scfg.denoise_loss_prob:
            loss = loss + _denoising_loss(tr, pair.generator, x0, cond, scfg)
        return loss, b

    summary = trainer.run(step, "dmd")
    _export_pair(stage_dir, trainer, pair, cfg, scfg, "dmd")
    return summary


def reflected_index(i: int, length: int) -> int:
    """Frame i of a clip of ``length`` frames played back and forth: 0 1 .. n-1 n-2 .. 0 1 .."""
    if length == 1:
        return 0
    m = i % (2 * length - 2)
    return m if m < length else 2 * length - 2 - m


def rollout_frame_indices(num_frames: int, start: int, frames: int) -> list[int]:
    """The clip frames behind rollout frames [start, start + frames) of a clip of ``num_frames``
    frames played back and forth (:func:`reflected_index`)."""
    return [reflected_index(i, num_frames) for i in range(start, start + frames)]


def _long_conditions(windows: LatentWindows, clips: list[int], start: int, frames: int, anchor: int) -> Conditions:
    """Conditions of rollout frames [start, start + frames) per row, ego relative to rollout frame ``anchor``."""
    items = []
    for ci in clips:
        clip, arr = windows.clips[ci], windows.arrays[ci]
        idx = rollout_frame_indices(clip.num_frames, start, frames)
        first = clip.frames[reflected_index(anchor, clip.num_frames)].ego
        ego = np.stack([clip.frames[i].ego_pose_condition(first) for i in idx]).astype(np.float32)
        fields = {k: getattr(arr, k)[idx] for k in arr.TIME_FIELDS}
        items.append(replace(arr, **{**fields, "ego": ego}))
    return Conditions.collate(items)


def rollout_starts(
    windows: LatentWindows, rng: np.random.Generator, batch: int, prefix: int
) -> tuple[list[int], torch.Tensor, Conditions]:
    """A fresh long rollout per row: random clips, their first ``prefix`` latents (B, prefix, ...)
    and those frames' conditions (ego relative to rollout frame 0)."""
    clips = [int(i) for i in rng.integers(len(windows.clips), size=batch)]
    first = torch.stack(
        [windows.latents[ci][rollout_frame_indices(windows.clips[ci].num_frames, 0, prefix)] for ci in clips]
    ).float()
    return clips, first, _long_conditions(windows, clips, 0, prefix, 0)


def _long_stage(run: StageRun) -> dict:
    windows, run_dir, stage_dir = run.windows, run.run_dir, run.stage_dir
    cfg, scfg, tcfg = run.cfg, run.scfg, run.tcfg
    pair, real = _pair(run_dir, "dmd", cfg)
    guidance = real_score_guidance(real, scfg)
    trainer = run.trainer(pair, "long")
    c, p = cfg.clip.chunk_frames, scfg.prefix_frames
    clip_frames = scfg.long_clip_chunks * c
    skip_frames = scfg.long_skip_chunks * c
    real_frames = p + _max_chunks(windows, cfg, scfg) * c  # the real windows of the denoising term
    engine = StreamingEngine(pair.generator, scfg, trainer.gen)
    state: dict = {"clips": None}

    def start(tr: Trainer) -> None:
        clips, first, cond = rollout_starts(windows, tr.rng, tcfg.batch_size, p)
        engine.start(first, cond)
        state["clips"] = clips

    def generate(cond: Conditions, grad: bool, exit_step: int | None) -> torch.Tensor:
        return torch.cat(
            [
                engine.step(cond.frames(k * c, (k + 1) * c), exit_step=exit_step, grad=grad)
                for k in range(scfg.long_clip_chunks)
            ],
            dim=1,
        )

    def advance(clips: list[int]) -> None:
        """``long_skip_chunks`` untrained chunks between two trained clips (see StudentConfig)."""
        with torch.no_grad():
            for _ in range(scfg.long_skip_chunks):
                engine.step(_long_conditions(windows, clips, engine.position, c, 0))

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        fresh = state["clips"] is None or engine.position + skip_frames + clip_frames > scfg.long_frames
        if fresh:
            start(tr)  # and trains the new rollout's first clip at once
        else:
            advance(state["clips"])
        pos, clips = engine.position, state["clips"]
        controls = _long_conditions(windows, clips, pos, clip_frames, 0)  # the rollout's own frame
        scored = _long_conditions(windows, clips, pos, clip_frames, pos)  # the teacher sees the clip alone
        for _ in range(scfg.critic_updates):
            snap = engine.snapshot()  # extra samples from the same context, then rewind
            with torch.no_grad():
                fake = generate(controls, False, None)
            engine.restore(snap)
            _critic_update(tr, pair, fake, scored, cfg)
        clip = generate(controls, True, int(torch.randint(scfg.num_steps, (1,), generator=tr.gen)))
        b = clip.shape[0]
        t, noise = dmd_times(b, scfg, tr.gen), _noise(clip.shape, tr)
        loss = dmd_generator_loss(real, pair.critic, clip, scored, t, noise, guidance=guidance, dmd_norm=scfg.dmd_norm)
        if tr.rng.random() < scfg.denoise_loss_prob:
            x0, cond = _sample(windows, tr.rng, b, real_frames)
            loss = loss + _denoising_loss(tr, pair.generator, x0, cond, scfg)
        return loss, b * clip_frames

    summary = trainer.run(step, "long")
    _export_pair(stage_dir, trainer, pair, cfg, scfg, "long")
    return {**summary, "rollout_frames": engine.position}


def run_student_stage(
    stage: str,
    data_dir: Path,
    stage_dir: Path,
    cfg: ModelConfig,
    tcfg: TrainConfig,
    progress: bool,
    student: StudentConfig | None = None,
    base: str | Path | None = None,
) -> dict:
    """Dispatch one student stage (called by :func:`world_model.train.stages.train_stage`).
    ``base``: ``compress`` only, its source student (:func:`compress_stage.load_source`)."""
    if stage not in STUDENT_STAGES:
        raise ValueError(f"unknown student stage {stage!r}; choose one of {STUDENT_STAGES}")
    scfg = student or StudentConfig()
    if stage != "compress" and scfg.compress_object_weight:
        raise ValueError(f"--compress-object-weight is a setting of --stage compress, not of {stage!r}")
    run_dir = stage_dir.parent
    if stage == "compress":
        from world_model.train.compress_stage import compress_stage, load_source

        source = load_source(base, run_dir)  # a bundle source first brings its VAE into the run
        windows = _windows(data_dir, run_dir, cfg)
        torch.manual_seed(tcfg.seed)
        return compress_stage(StageRun(windows, run_dir, stage_dir, cfg, scfg, tcfg, progress), source)
    _need(run_dir / PREDECESSOR[stage] / EXPORT, PREDECESSOR[stage])
    windows = _windows(data_dir, run_dir, cfg)
    torch.manual_seed(tcfg.seed)
    stage_fn = {"tf": _tf_stage, "ode": _ode_stage, "dmd": _dmd_stage, "long": _long_stage}[stage]
    return stage_fn(StageRun(windows, run_dir, stage_dir, cfg, scfg, tcfg, progress))
