"""Training stages of the world model (``vae``, ``teacher``), checkpoints and EMA."""

from world_model.train.checkpoint import load_latest, save_checkpoint
from world_model.train.ema import EMA
from world_model.train.stages import STAGES, load_teacher, load_vae, train_stage
from world_model.train.trainer import TrainConfig, Trainer, TrainingDivergedError

__all__ = [
    "EMA",
    "STAGES",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "load_latest",
    "load_teacher",
    "load_vae",
    "save_checkpoint",
    "train_stage",
]
