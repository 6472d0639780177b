"""What every stage works with: the options it trains with (:class:`StageOptions`, each stage's
own type extends it), the run-time choices of the process (:class:`StageRuntime`) and
:class:`StageRun`: its data, the run's folders, its configs and the process's place (device, rank)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from world_model.model.config import ModelConfig
from world_model.train.data import LatentWindows
from world_model.train.device import TrainPlace
from world_model.train.exports import open_run_latents
from world_model.train.trainer import LoopOptions, TrainConfig, Trainer


@dataclass(frozen=True, kw_only=True)
class StageOptions:
    """What every stage trains with: the model config and the schedule; the options type of the
    stages that take nothing more (a stage's own type extends it: ``Stage.options``).

    ``config`` overrides ``preset``'s config (it must then stay the same across resumes). ``steps``,
    ``batch_size`` (the global batch), ``lr`` and ``ckpt_every``: None takes the stage's defaults."""

    preset: str = "default"
    config: ModelConfig | None = None
    steps: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    ckpt_every: int | None = None
    seed: int = 0


@dataclass(frozen=True, kw_only=True)
class StageRuntime:
    """How this process trains a stage: run-time choices, which checkpoints and their configs do not
    record.

    ``dtype``: the DiTs' autocast, "auto" (bf16 when the config asks for it and the device
    multiplies bf16 faster than float32, :func:`world_model.precision.bf16_is_fast`), "float32" or
    "bfloat16". ``device``: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``; ``place`` (a process of a
    ``torchrun`` group, :func:`world_model.train.device.init_place`) overrides it.
    ``compile_model``: ``torch.compile`` the trained networks. ``time_limit_s``: the stage stops this
    many seconds after :func:`~world_model.train.stages.train_stage` is called, its setup (caches,
    rollouts) counted, checkpointed and exported, even short of its steps (after one step at least)."""

    progress: bool = True
    dtype: str = "auto"
    device: str = "cpu"
    place: TrainPlace | None = None
    compile_model: bool = False
    time_limit_s: float | None = None


@dataclass(frozen=True)
class StageRun:
    """One stage's inputs: the dataset, ``RUN/`` (the earlier stages' exports), ``RUN/<stage>/``
    (this stage's checkpoints and export), the model and training configs, where the process trains
    (:class:`TrainPlace`) and how it runs the loop (:class:`LoopOptions`)."""

    data_dir: Path
    run_dir: Path
    stage_dir: Path
    cfg: ModelConfig
    tcfg: TrainConfig
    place: TrainPlace
    loop: LoopOptions = LoopOptions()

    def trainer(self, model: nn.Module, stage: str, resume_keys: dict | None = None, **meta: object) -> Trainer:
        """The stage's :class:`Trainer` (checkpoints in ``stage_dir``, metadata naming the stage and,
        unless ``meta`` gives another, the run's model config)."""
        info = {"stage": stage, "model_config": self.cfg.to_dict(), **meta}
        return Trainer(self.stage_dir, model, self.tcfg, info, resume_keys, self.place, self.loop)

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
