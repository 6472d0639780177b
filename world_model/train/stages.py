"""Training stages ``vae`` and ``teacher`` (§4.1, bidirectional mid-training) and their exports.

A run directory holds one sub-directory per stage (later issues add the student stages)::

    RUN_DIR/vae/       checkpoints/, model.safetensors + model.json (EMA weights), metrics.json
    RUN_DIR/teacher/   checkpoints/, latents/ (the run's latent cache, every stage), model.safetensors + model.json
    RUN_DIR/reference/ the reference-conditioned model (world_model.train.reference_stage)
    RUN_DIR/lora/CASE/ one LoRA adapter per long-tail case (world_model.train.lora_stage)

The teacher stage reads the VAE export of the same run. Rerunning a command resumes from the
stage's latest checkpoint; a finished stage rerun with a larger ``steps`` continues training.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from world_model.data.clips import write_json_atomic
from world_model.model.config import ModelConfig, get_preset
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import flow_matching_loss, sample_timesteps
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.text import make_text_encoder
from world_model.model.vae import SensorVAE, images_to_cameras, images_to_lidar, kl_loss, weighted_l1
from world_model.precision import check_dtype, dit_precision, resolve_bf16
from world_model.student.config import StudentConfig
from world_model.train.checkpoint import export_weights
from world_model.train.data import (
    FrameSampler,
    LatentWindows,
    cached_latents,
    file_digest,
    latent_cache_dir,
    load_clips,
)
from world_model.train.trainer import TrainConfig, Trainer

# tf..compress: student_stages.py
STAGES = ("vae", "teacher", "tf", "ode", "dmd", "long", "compress", "reference", "lora")
EXPORT = "model"  # model.safetensors + model.json in each stage directory

# Per stage: (batch size, learning rate, checkpoint period). Batch sizes are CPU-sized.
STAGE_DEFAULTS = {
    "vae": (16, 2e-3, 100),
    "teacher": (4, 1e-3, 100),
    "reference": (4, 5e-4, 100),
    "lora": (4, 1e-3, 50),
    "tf": (4, 5e-4, 100),
    "ode": (4, 5e-4, 20),  # a step runs a 20-step guided ODE: checkpoint often
    "dmd": (2, 1e-4, 10),  # each step = 1 + critic_updates self-rollouts
    "long": (2, 5e-5, 10),
    "compress": (2, 2e-4, 10),  # each step rolls two students out together
}
DEFAULT_STEPS = {"tiny": 50, "default": 3000, "gpu": 100_000}
# Stages whose steps cost far more than a teacher step get their own default per preset. Sized for
# the 2-core CPU (docs/MODEL_CARD.md lists the measured seconds per step): one ``ode`` step runs the
# TF model's 20-step guided ODE, one ``dmd``/``long`` step runs 1 + critic_updates self-rollouts.
STAGE_STEPS = {"default": {"tf": 500, "ode": 80, "dmd": 50, "long": 20, "reference": 800}}
EVAL_FRAMES = 32  # frames used for the VAE's reconstruction metrics
STATS_FRAMES = 64  # frames used to fit the latent normalization


def load_vae(path: str | Path) -> SensorVAE:
    """A VAE exported by the ``vae`` stage (``.../vae/model``, with or without suffix)."""
    path = Path(path).with_suffix("")
    cfg = ModelConfig.from_dict(json.loads(path.with_suffix(".json").read_text())["model_config"])
    vae = SensorVAE(cfg)
    vae.load_state_dict(_load(path))
    return vae.eval()


def load_teacher(path: str | Path) -> MultiViewDiT:
    """A DiT exported by the ``teacher`` stage."""
    path = Path(path).with_suffix("")
    cfg = ModelConfig.from_dict(json.loads(path.with_suffix(".json").read_text())["model_config"])
    model = MultiViewDiT(cfg)
    model.load_state_dict(_load(path))
    return model.eval()


def _load(path: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    file = path.with_suffix(".safetensors")
    if not file.exists():
        raise FileNotFoundError(f"{file} does not exist; run the stage that exports it first")
    return load_file(str(file))


# The config sections a stage's weights depend on; None = the whole config. The VAE ignores the
# DiT, so re-sizing the DiT of a preset keeps a trained VAE usable.
STAGE_CONFIG_SECTIONS: dict[str, tuple[str, ...] | None] = {"vae": ("sensors", "vae")}
# Full-depth bidirectional models: the student-only settings do not touch their weights.
TEACHER_WEIGHT_STAGES = ("teacher", "reference")


def _stage_config(stage_dir: Path, stage: str, preset: str, config: ModelConfig | None) -> ModelConfig:
    cfg = config or get_preset(preset)
    saved = stage_dir / "model_config.json"
    sections = STAGE_CONFIG_SECTIONS.get(stage)

    def relevant(c: ModelConfig) -> object:
        if stage in TEACHER_WEIGHT_STAGES:
            return c.teacher_settings()
        return c if sections is None else tuple(getattr(c, name) for name in sections)

    if saved.exists():
        prev = ModelConfig.from_dict(json.loads(saved.read_text()))
        if relevant(prev) != relevant(cfg):
            raise ValueError(
                f"{stage_dir} was started with preset {prev.name!r} and a different config; "
                "use the same preset to resume, or a new run directory"
            )
    else:
        stage_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(saved, cfg.to_dict())
    return cfg


def _train_config(
    stage: str,
    cfg: ModelConfig,
    steps: int | None,
    batch_size: int | None,
    lr: float | None,
    ckpt_every: int | None,
    seed: int,
) -> TrainConfig:
    b, l, every = STAGE_DEFAULTS[stage]
    preset_steps = STAGE_STEPS.get(cfg.name, {}).get(stage, DEFAULT_STEPS.get(cfg.name, DEFAULT_STEPS["default"]))
    n = steps if steps is not None else preset_steps
    if n < 1:
        raise ValueError(f"steps must be >= 1, got {n}")
    return TrainConfig(steps=n, batch_size=batch_size or b, lr=lr or l, ckpt_every=ckpt_every or every, seed=seed)


# -- vae ---------------------------------------------------------------------------------------


@torch.no_grad()
def vae_metrics(vae: SensorVAE, sampler: FrameSampler) -> dict[str, float]:
    """Camera PSNR (dB, uint8 images) and LiDAR range MAE (m, on true returns) + no-return accuracy."""
    cfg = vae.cfg
    spec = cfg.sensors.lidar
    se, count, abs_err, n_ret, nr_ok, n_all = 0.0, 0, 0.0, 0, 0, 0
    for ci, f in sampler.eval_frames(EVAL_FRAMES):
        clip = sampler.clips[ci]
        cams = np.asarray(clip.cameras[f])
        x = torch.stack([sampler.image(ci, f, v) for v in range(cfg.sensors.num_views)])
        rec = vae.decode(vae.encode(x))
        se += float(((images_to_cameras(rec[:-1]).astype(np.float64) - cams) ** 2).sum())
        count += cams.size
        truth = np.asarray(clip.lidar[f], dtype=np.float32)
        pred = images_to_lidar(rec[-1], spec, cfg.vae.lidar_no_return_fraction)
        ret = truth > spec.no_return
        abs_err += float(np.abs(pred - truth)[ret].sum())
        n_ret += int(ret.sum())
        nr_ok += int(((pred > spec.no_return) == ret).sum())
        n_all += truth.size
    mse = se / max(count, 1)
    return {
        "camera_psnr_db": 10 * math.log10(255.0**2 / max(mse, 1e-10)),
        "lidar_range_mae_m": abs_err / max(n_ret, 1),
        "lidar_return_accuracy": nr_ok / max(n_all, 1),
    }


def _vae_stage(data_dir: Path, stage_dir: Path, cfg: ModelConfig, tcfg: TrainConfig, progress: bool) -> dict:
    clips = load_clips(data_dir, cfg)
    sampler = FrameSampler(clips, cfg)
    torch.manual_seed(tcfg.seed)
    vae = SensorVAE(cfg)
    trainer = Trainer(stage_dir, vae, tcfg, {"stage": "vae", "model_config": cfg.to_dict()}, progress)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        images, is_lidar, weights = sampler.sample(tr.rng, tcfg.batch_size)
        mean, logvar = vae.posterior(images)
        z = mean + (0.5 * logvar).exp() * torch.randn(mean.shape, generator=tr.gen)
        err = weighted_l1(vae.decode_raw(z), images, weights)
        weight = torch.where(is_lidar, cfg.vae.lidar_loss_weight, 1.0)
        return (err * weight).mean() + cfg.vae.kl_weight * kl_loss(mean, logvar), len(images)

    summary = trainer.run(step, "vae")
    final = SensorVAE(cfg)
    final.load_state_dict(trainer.ema.model_state(vae))
    stats_rng = np.random.default_rng(tcfg.seed)
    final.set_latent_stats(sampler.sample(stats_rng, STATS_FRAMES).images)
    final.eval()
    metrics = vae_metrics(final, sampler)
    export_weights(
        stage_dir / EXPORT,
        final.state_dict(),
        {"stage": "vae", "step": trainer.step, "model_config": cfg.to_dict(), "metrics": metrics},
    )
    write_json_atomic(stage_dir / "metrics.json", {"step": trainer.step, **metrics})
    return {**summary, "metrics": metrics}


# -- teacher -----------------------------------------------------------------------------------


def _teacher_stage(data_dir: Path, stage_dir: Path, cfg: ModelConfig, tcfg: TrainConfig, progress: bool) -> dict:
    vae_path = stage_dir.parent / "vae" / EXPORT
    if not vae_path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(
            f"the teacher stage needs a trained VAE at {vae_path}.safetensors; "
            "run --stage vae with the same --run first"
        )
    vae = load_vae(vae_path)
    if vae.cfg.vae.model_settings() != cfg.vae.model_settings() or vae.cfg.sensors != cfg.sensors:
        raise ValueError(f"the VAE in {vae_path.parent} was trained for preset {vae.cfg.name!r}, not {cfg.name!r}")
    clips = load_clips(data_dir, cfg)
    digest = file_digest(vae_path.with_suffix(".safetensors"))
    latents = [cached_latents(c, vae, latent_cache_dir(stage_dir.parent), digest) for c in clips]
    windows = LatentWindows(clips, latents, cfg, make_text_encoder(cfg.text), VaeCropEncoder(vae))
    torch.manual_seed(tcfg.seed)
    model = MultiViewDiT(cfg)
    trainer = Trainer(stage_dir, model, tcfg, {"stage": "teacher", "model_config": cfg.to_dict()}, progress)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        x0, cond = windows.sample(tr.rng, tcfg.batch_size)
        b = x0.shape[0]
        cond = cond.with_drop(torch.rand(b, generator=tr.gen) < cfg.flow.cond_drop_prob)
        t = sample_timesteps((b,), cfg.flow, tr.gen)
        noise = torch.randn(x0.shape, generator=tr.gen)
        loss = flow_matching_loss(lambda xt, tt: model(xt, tt, cond), x0, t, noise)
        return loss, b * x0.shape[1]

    summary = trainer.run(step, "teacher")
    export_weights(
        stage_dir / EXPORT,
        trainer.ema.model_state(model),
        {"stage": "teacher", "step": trainer.step, "model_config": cfg.to_dict()},
    )
    return summary


def train_stage(
    stage: str,
    data_dir: str | Path,
    run_dir: str | Path,
    preset: str = "default",
    steps: int | None = None,
    *,
    batch_size: int | None = None,
    lr: float | None = None,
    ckpt_every: int | None = None,
    seed: int = 0,
    progress: bool = True,
    config: ModelConfig | None = None,
    case: str | None = None,
    case_data: str | Path | None = None,
    case_clips: list[str] | None = None,
    base: str | Path | None = None,
    lora_box_weight: float = 0.0,
    lora_rank: int | None = None,
    student: StudentConfig | None = None,
    dtype: str = "auto",
) -> dict:
    """Train (or resume) one stage into ``run_dir/<stage>/``; returns a summary dict.

    ``config`` overrides the preset's config (it must then stay the same across resumes);
    ``student`` configures the student stages (``tf``, ``ode``, ``dmd``, ``long``, ``compress``);
    ``compress``'s ``base`` is its source student (default ``run_dir/long/model``; a bundle or an
    exported student: :func:`world_model.train.compress_stage.load_source`).
    ``lora`` only: ``case`` names the adapter (and the rare category), ``case_data`` an extra
    dataset of rare clips, ``case_clips`` explicit rare clip names, ``base`` the model adapted
    (default ``run_dir/teacher/model``), ``lora_box_weight`` the extra loss weight inside the rare
    object's boxes (``LoraStageConfig.box_weight``), ``lora_rank`` the adapter's rank (None: ``LoraConfig``'s).
    ``dtype``: the DiTs' autocast in this process, "auto" (bf16 when the config asks for it and this
    CPU multiplies bf16 natively: elsewhere bf16 is emulated and several times slower), "float32"
    or "bfloat16". A run-time choice: checkpoints and their configs do not record it.
    """
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; choose one of {STAGES}")
    if stage != "lora" and lora_box_weight:
        raise ValueError(f"--lora-box-weight is a setting of --stage lora, not of {stage!r}")
    if stage not in ("lora", "compress") and base is not None:
        raise ValueError(f"--base is a setting of --stage lora and --stage compress, not of {stage!r}")
    if stage != "lora" and lora_rank is not None:
        raise ValueError(f"--lora-rank is a setting of --stage lora, not of {stage!r}")
    check_dtype(dtype)
    if stage == "lora":
        from world_model.lora import LoraConfig
        from world_model.train.lora_stage import LORA_STEPS, LoraStageConfig, lora_stage_dir

        lora = LoraConfig() if lora_rank is None else LoraConfig().with_rank(lora_rank)
        scfg = LoraStageConfig(box_weight=lora_box_weight, lora=lora)  # bad settings refused before any write
        stage_dir = lora_stage_dir(run_dir, case)
        steps = LORA_STEPS if steps is None else steps
    else:
        stage_dir = Path(run_dir) / stage
    data_dir = Path(data_dir)
    cfg = _stage_config(stage_dir, stage, preset, config)
    tcfg = _train_config(stage, cfg, steps, batch_size, lr, ckpt_every, seed)
    precision = dit_precision(resolve_bf16(dtype, cfg.dit.autocast_bf16, "cpu"))
    if stage in ("vae", "teacher"):
        run = _vae_stage if stage == "vae" else _teacher_stage
    elif stage == "reference":
        from world_model.train.reference_stage import reference_stage as run
    elif stage == "lora":
        from functools import partial

        from world_model.train.lora_stage import lora_stage

        run = partial(lora_stage, case=case, case_data=case_data, case_clips=case_clips, base=base, scfg=scfg)
    else:
        from world_model.train.student_stages import run_student_stage  # it imports this module

        with precision:
            out = run_student_stage(stage, data_dir, stage_dir, cfg, tcfg, progress, student, base)
        return {"stage": stage, "stage_dir": str(stage_dir), **out}
    with precision:
        out = run(data_dir, stage_dir, cfg, tcfg, progress)
    return {"stage": stage, "stage_dir": str(stage_dir), **out}
