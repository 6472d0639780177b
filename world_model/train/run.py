"""What every stage works with: :class:`StageRun`, its data, the run's folders, its configs and
the process's place (device, rank)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from world_model.model.config import ModelConfig
from world_model.student.config import StudentConfig
from world_model.train.data import LatentWindows
from world_model.train.device import TrainPlace
from world_model.train.exports import open_run_latents
from world_model.train.trainer import TrainConfig, Trainer


@dataclass(frozen=True)
class StageRun:
    """One stage's inputs: the dataset, ``RUN/`` (the earlier stages' exports), ``RUN/<stage>/``
    (this stage's checkpoints and export), the model, training and student configs, and where the
    process trains (:class:`TrainPlace`)."""

    data_dir: Path
    run_dir: Path
    stage_dir: Path
    cfg: ModelConfig
    tcfg: TrainConfig
    place: TrainPlace
    progress: bool = True
    scfg: StudentConfig = field(default_factory=StudentConfig)
    compile_model: bool = False
    deadline: float | None = None  # time.perf_counter() at which training stops (Trainer)

    def trainer(self, model: nn.Module, stage: str, resume_keys: dict | None = None, **meta: object) -> Trainer:
        """The stage's :class:`Trainer` (checkpoints in ``stage_dir``, metadata naming the stage and,
        unless ``meta`` gives another, the run's model config)."""
        info = {"stage": stage, "model_config": self.cfg.to_dict(), **meta}
        return Trainer(
            self.stage_dir,
            model,
            self.tcfg,
            info,
            self.progress,
            resume_keys,
            self.place,
            self.compile_model,
            self.deadline,
        )

    def latents(self, stage: str) -> LatentWindows:
        """The dataset in the run's latents (:func:`open_run_latents`); under ``torchrun`` rank 0
        encodes the clips missing from the cache first, and the other ranks then read them."""
        if not self.place.is_main:
            self.place.barrier()
        windows = open_run_latents(self.data_dir, self.run_dir, self.cfg, stage, self.place.device)
        if self.place.is_main:
            self.place.barrier()
        return windows

    @property
    def device(self) -> torch.device:
        return self.place.device
