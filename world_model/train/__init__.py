"""Training of the world model: the stages (vae, decoder, teacher, tf, ode, dmd, long, reference,
rollout_decoder, lora), their checkpoints, exports and EMA. The command line: ``python -m world_model.train``
(= ``m4world train``).

The names below load on first use, so that the command line's parser
(:mod:`world_model.train.cli`) builds without importing torch.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

_EXPORTS = {
    "EMA": "world_model.train.ema",
    "STAGES": "world_model.train.stages",
    "StageOptions": "world_model.train.run",
    "StageRuntime": "world_model.train.run",
    "TrainConfig": "world_model.train.trainer",
    "Trainer": "world_model.train.trainer",
    "TrainingDivergedError": "world_model.train.trainer",
    "load_latest": "world_model.train.checkpoint",
    "load_student": "world_model.train.exports",
    "load_teacher": "world_model.train.exports",
    "load_vae": "world_model.train.exports",
    "open_run_latents": "world_model.train.exports",
    "save_checkpoint": "world_model.train.checkpoint",
    "stage_options": "world_model.train.stages",
    "train_stage": "world_model.train.stages",
}
__all__ = [
    "EMA",
    "STAGES",
    "StageOptions",
    "StageRuntime",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "load_latest",
    "load_student",
    "load_teacher",
    "load_vae",
    "open_run_latents",
    "save_checkpoint",
    "stage_options",
    "train_stage",
]

if TYPE_CHECKING:
    from world_model.train.checkpoint import load_latest, save_checkpoint
    from world_model.train.ema import EMA
    from world_model.train.exports import load_student, load_teacher, load_vae, open_run_latents
    from world_model.train.run import StageOptions, StageRuntime
    from world_model.train.stages import STAGES, stage_options, train_stage
    from world_model.train.trainer import TrainConfig, Trainer, TrainingDivergedError


def __getattr__(name: str) -> object:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'world_model.train' has no attribute {name!r}")
    return getattr(import_module(_EXPORTS[name]), name)
