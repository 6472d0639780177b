"""What the stages export and read back: the stage exports of a run, their loaders and checks, and
the run's cached latents as :class:`~world_model.train.data.LatentWindows`.

Each stage directory holds its final weights as ``model.safetensors`` + ``model.json`` (the
config and metadata); the ``dmd`` and ``long`` stages also export their critic
(``critic.safetensors`` + ``critic.json``).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import torch

from world_model.model.config import ModelConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.text import make_text_encoder
from world_model.model.vae import SensorVAE
from world_model.student.config import StudentConfig
from world_model.train.data import (
    LatentWindows,
    cached_latents,
    cached_layouts,
    dataset_stamp,
    encoder_digest,
    latent_cache_dir,
    layout_cache_dir,
    load_clips,
    remember_last,
)

EXPORT = "model"  # model.safetensors + model.json in each stage directory
CRITIC = "critic"  # RUN/dmd/critic.safetensors + critic.json


def load_weights(path: Path) -> dict[str, torch.Tensor]:
    """The tensors of ``<path>.safetensors`` on the CPU."""
    from safetensors.torch import load_file

    file = path.with_suffix(".safetensors")
    if not file.exists():
        raise FileNotFoundError(f"{file} does not exist; run the stage that exports it first")
    return load_file(str(file))


def _model_config(path: Path) -> ModelConfig:
    return ModelConfig.from_dict(json.loads(path.with_suffix(".json").read_text())["model_config"])


def load_vae(path: str | Path) -> SensorVAE:
    """A VAE exported by the ``vae`` stage (``.../vae/model``, with or without suffix)."""
    path = Path(path).with_suffix("")
    vae = SensorVAE(_model_config(path))
    vae.load_state_dict(load_weights(path))
    return vae.eval()


def load_teacher(path: str | Path) -> MultiViewDiT:
    """A DiT exported by the ``teacher`` stage (or any stage exporting a DiT)."""
    path = Path(path).with_suffix("")
    model = MultiViewDiT(_model_config(path))
    model.load_state_dict(load_weights(path))
    return model.eval()


def export_student_config(path: str | Path) -> StudentConfig:
    """The :class:`StudentConfig` a student export was trained with, read from its metadata alone."""
    meta = json.loads(Path(path).with_suffix("").with_suffix(".json").read_text())
    return StudentConfig.from_dict(meta.get("student_config", {}))


def load_student(path: str | Path) -> tuple[MultiViewDiT, StudentConfig]:
    """A student exported by ``tf``/``ode``/``dmd``/``long``/``steps``, with its :class:`StudentConfig`."""
    return load_teacher(Path(path).with_suffix("")), export_student_config(path)


def require_export(path: Path, stage: str) -> Path:
    """``path`` (a stage export without suffix) when its weights exist, else an error naming the stage to run."""
    if not path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(f"{path}.safetensors is missing; run --stage {stage} with the same --run first")
    return path


def run_vae(run_dir: Path, cfg: ModelConfig, stage: str) -> tuple[SensorVAE, str]:
    """The run's VAE export, checked against ``cfg``, and its :func:`encoder_digest` (the latent
    cache's key)."""
    path = run_dir / "vae" / EXPORT
    if not path.with_suffix(".safetensors").exists():
        raise FileNotFoundError(
            f"--stage {stage} needs a trained VAE at {path}.safetensors; run --stage vae with the same --run first"
        )
    vae = load_vae(path)
    if vae.cfg.vae.model_settings() != cfg.vae.model_settings() or vae.cfg.sensors != cfg.sensors:
        raise ValueError(f"the VAE in {path.parent} was trained for preset {vae.cfg.name!r}, not {cfg.name!r}")
    return vae, encoder_digest(vae)


def run_latents(
    clips: list, vae: SensorVAE, vae_digest: str, run_dir: Path, device: torch.device | str = "cpu"
) -> list[torch.Tensor]:
    """Each clip's latents (T, V, C, h, w) on the CPU, through the run's latent cache: what is
    missing is encoded by a copy of ``vae`` on ``device``."""
    device = torch.device(device)
    encoder = vae if device.type == "cpu" else copy.deepcopy(vae).to(device)
    return [cached_latents(c, encoder, latent_cache_dir(run_dir), vae_digest) for c in clips]


def latent_windows(
    clips: list,
    vae: SensorVAE,
    vae_digest: str,
    run_dir: Path,
    cfg: ModelConfig,
    device: torch.device | str = "cpu",
) -> LatentWindows:
    """``clips`` encoded by ``vae`` on ``device`` (through the run's latent cache) with their
    conditions, their layout rasters from the run's layout cache."""
    latents = run_latents(clips, vae, vae_digest, run_dir, device)
    layouts = cached_layouts(clips, cfg, layout_cache_dir(run_dir))
    return LatentWindows(clips, latents, cfg, make_text_encoder(cfg.text), VaeCropEncoder(vae), layouts)


def open_run_latents(
    data_dir: str | Path, run_dir: Path, cfg: ModelConfig, stage: str, device: torch.device | str = "cpu"
) -> LatentWindows:
    """The dataset's clips in the run's VAE latents (encoded once on ``device``, cached in the run)
    with their conditions: what every stage after ``vae`` trains on. The same windows as the last
    call of this process for an unchanged dataset, run VAE and config (:func:`remember_last`)."""
    vae, digest = run_vae(run_dir, cfg, stage)
    stamp = dataset_stamp(data_dir)
    run_key = (str(Path(run_dir).resolve()), digest, json.dumps(cfg.to_dict(), sort_keys=True), str(device))
    return remember_last(
        "run_latents",
        None if stamp is None else (stamp, run_key),
        lambda: latent_windows(load_clips(data_dir, cfg), vae, digest, run_dir, cfg, device),
    )
