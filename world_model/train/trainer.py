"""The training loop every stage shares: resume, step, EMA, progress, checkpoints, NaN guard.

Progress goes to a tqdm bar and, for background jobs without a terminal, to
``<stage_dir>/progress.json`` (step, total, loss, throughput, ETA), rewritten atomically at most
every ``PROGRESS_PERIOD_S`` seconds and at every checkpoint: ``cat`` it to follow a run.

Determinism: all randomness of a stage (data sampling, noise, timesteps, condition dropout) comes
from one ``numpy.random.Generator`` and one ``torch.Generator`` (on the training device) owned by
the :class:`Trainer`; both are checkpointed, so a run killed and restarted continues exactly as if
uninterrupted. Checkpoints hold CPU tensors and load onto any device; a run resumed on another
kind of device re-seeds its torch generator (a device's generator state cannot move to another).

Under ``torchrun`` every rank runs the same loop (:mod:`world_model.train.device`): gradients are
averaged over the ranks before each optimizer step, and rank 0 alone writes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from world_model.data.clips import write_json_atomic
from world_model.train.checkpoint import load_latest, save_checkpoint
from world_model.train.device import TrainPlace
from world_model.train.ema import EMA

T = TypeVar("T")
PROGRESS_PERIOD_S = 30.0
LOSS_WINDOW = 50  # steps in the progress file's running-mean loss


class TrainingDivergedError(RuntimeError):
    """The loss became NaN/inf; the last good checkpoint was kept."""


@dataclass(frozen=True)
class TrainConfig:
    steps: int
    batch_size: int
    lr: float
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    warmup_steps: int = 20
    ema_decay: float = 0.999
    ckpt_every: int = 100
    keep_checkpoints: int = 2
    seed: int = 0


# StepFn(trainer) -> (loss, samples in the batch): uses trainer.rng / trainer.gen for randomness.
StepFn = Callable[["Trainer"], tuple[torch.Tensor, int]]


@dataclass(frozen=True)
class LoopOptions:
    """How this process runs a stage's loop: run-time choices that no checkpoint records.

    ``progress``: a tqdm bar (rank 0). ``compile_model``: ``torch.compile`` the model's forward
    (each trained network of a container module). ``deadline``: a :func:`time.perf_counter` time at
    which :meth:`Trainer.run` stops, checkpointed, even short of ``tcfg.steps`` (rerunning resumes
    towards ``tcfg.steps``); it takes at least one step, so that a stage whose setup used up its
    time still leaves a checkpoint."""

    progress: bool = True
    compile_model: bool = False
    deadline: float | None = None


class Trainer:
    def __init__(
        self,
        stage_dir: Path,
        model: nn.Module,
        tcfg: TrainConfig,
        meta: dict,
        resume_keys: dict[str, object] | None = None,
        place: TrainPlace | None = None,
        loop: LoopOptions | None = None,
    ):
        """``resume_keys``: entries of ``meta`` a resumed run must share with its checkpoint (a
        setting that changes the objective mid-run), else :meth:`resume` raises ``ValueError``; each
        maps to the value a checkpoint without the entry was trained with. ``place``: the device and
        rank (default: one process on the CPU); the model moves there. ``loop``: :class:`LoopOptions`."""
        loop = loop or LoopOptions()
        self.deadline = loop.deadline
        self.resume_keys = dict(resume_keys or {})
        self.place = place or TrainPlace(torch.device("cpu"))
        self.dir = Path(stage_dir)
        self.ckpt_dir = self.dir / "checkpoints"
        self.model = model.to(self.place.device)
        if loop.compile_model:
            own_forward = type(model).forward is not nn.Module.forward
            for m in [model] if own_forward else list(model.children()):
                m.compile()
        self.tcfg = tcfg
        self.meta = meta
        self.progress = loop.progress and self.place.is_main
        self.opt = torch.optim.AdamW(model.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)
        self.ema = EMA(model, tcfg.ema_decay)
        self.rng = np.random.default_rng(tcfg.seed)
        self.gen = torch.Generator(device=self.place.device).manual_seed(tcfg.seed)
        self.step = 0
        self.last_loss = float("nan")
        self.resumed_from: int | None = None

    # -- randomness of a step, on the training device --
    def rand(self, *shape: int) -> torch.Tensor:
        return torch.rand(shape, generator=self.gen, device=self.gen.device)

    def randn(self, *shape: int) -> torch.Tensor:
        return torch.randn(shape, generator=self.gen, device=self.gen.device)

    def randint(self, high: int, *shape: int) -> torch.Tensor:
        return torch.randint(high, shape, generator=self.gen, device=self.gen.device)

    def shard(self, x: T) -> T:
        """This rank's rows of a global batch ``x``, on the training device (:meth:`TrainPlace.shard`)."""
        return self.place.shard(x)

    # -- state --
    def resume(self) -> bool:
        ck = load_latest(self.ckpt_dir)
        if ck is None:
            return False
        for key, before in self.resume_keys.items():
            if ck.meta.get(key, before) != self.meta.get(key):
                raise ValueError(
                    f"{self.dir} was trained with {key}={ck.meta.get(key, before)!r} up to step {ck.step}, not "
                    f"{self.meta.get(key)!r}: resume it with the same setting, or train into a new --run"
                )
        self.model.load_state_dict(ck.tensors["model"])
        self.ema.load_state_dict(ck.tensors["ema"], ck.meta["ema_updates"])
        self.opt.load_state_dict(ck.train_state["optimizer"])
        if ck.meta.get("torch_rng_device", "cpu") == self.place.device.type:
            self.gen.set_state(ck.train_state["torch_rng"])
        else:  # another kind of device's generator state: continue from a seed of its own
            self.gen.manual_seed(self.tcfg.seed + ck.step)
        self.rng.bit_generator.state = ck.meta["numpy_rng"]
        self.step = ck.step
        self.last_loss = float(ck.meta.get("loss", float("nan")))
        self.resumed_from = ck.step
        return True

    def save(self) -> Path | None:
        """Write a checkpoint (rank 0; the others wait for it) and return its path (None elsewhere)."""
        if not self.place.is_main:
            self.place.barrier()
            return None
        meta = {
            **self.meta,
            "torch_rng_device": self.place.device.type,
            "numpy_rng": self.rng.bit_generator.state,
            "ema_updates": self.ema.updates,
            "loss": self.last_loss,
            "train_config": asdict(self.tcfg),
        }
        path = save_checkpoint(
            self.ckpt_dir,
            self.step,
            {"model": self.model.state_dict(), "ema": self.ema.state_dict()},
            {"optimizer": _to_cpu(self.opt.state_dict()), "torch_rng": self.gen.get_state()},
            meta,
            keep=self.tcfg.keep_checkpoints,
        )
        self.place.barrier()
        return path

    def write_progress(self, desc: str, losses: list[float], rate_steps: float, rate_samples: float) -> None:
        if not self.place.is_main:
            return
        recent = losses[-LOSS_WINDOW:]
        left = self.tcfg.steps - self.step
        write_json_atomic(
            self.dir / "progress.json",
            {
                "stage": desc,
                "step": self.step,
                "total_steps": self.tcfg.steps,
                "loss": self.last_loss,
                f"loss_mean_last_{LOSS_WINDOW}": sum(recent) / len(recent) if recent else None,
                "steps_per_s": rate_steps,
                "samples_per_s": rate_samples,
                "eta_s": left / rate_steps if rate_steps > 0 else None,
                "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            },
        )

    def _lr(self) -> float:
        return self.tcfg.lr * min(1.0, (self.step + 1) / max(1, self.tcfg.warmup_steps))

    # -- loop --
    def run(self, step_fn: StepFn, desc: str) -> dict:
        """Train until ``tcfg.steps`` or the time limit; returns a summary (losses, throughput, resume
        point, whether the time limit stopped it)."""
        self.resume()
        self.model.train()
        losses: list[float] = []
        samples, t0 = 0, time.perf_counter()
        last_report = t0
        timed_out = False
        bar = tqdm(
            total=self.tcfg.steps,
            initial=self.step,
            desc=desc,
            disable=not self.progress,
            dynamic_ncols=True,
            leave=False,
        )
        try:
            while self.step < self.tcfg.steps:
                for group in self.opt.param_groups:
                    group["lr"] = self._lr()
                loss, n = step_fn(self)
                value = self.place.mean(float(loss.detach()))
                if not math.isfinite(value):
                    raise TrainingDivergedError(
                        f"{desc}: loss is {value} at step {self.step + 1}; the last good checkpoint "
                        f"(if any) is kept in {self.ckpt_dir}. "
                        "Lower the learning rate or check the data, then rerun the same command to resume."
                    )
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                self.place.average_gradients(self.model)
                if self.tcfg.grad_clip > 0:
                    nn.utils.clip_grad_norm_(self.model.parameters(), self.tcfg.grad_clip)
                self.opt.step()
                self.ema.update(self.model)
                self.step += 1
                self.last_loss = value
                losses.append(value)
                samples += n * self.place.world_size
                now = time.perf_counter()
                rate = samples / max(now - t0, 1e-9)
                bar.set_postfix(loss=f"{value:.4f}", samples_per_s=f"{rate:.1f}")
                bar.update(1)
                timed_out = self._out_of_time(now)
                checkpoint = self.step % self.tcfg.ckpt_every == 0 or self.step == self.tcfg.steps or timed_out
                if checkpoint:
                    self.save()
                if checkpoint or now - last_report >= PROGRESS_PERIOD_S:
                    self.write_progress(desc, losses, len(losses) / max(now - t0, 1e-9), rate)
                    last_report = now
                if timed_out:
                    break
        finally:
            bar.close()
        elapsed = time.perf_counter() - t0
        return {
            "step": self.step,
            "losses": losses,
            "resumed_from": self.resumed_from,
            "samples_per_s": samples / elapsed if losses else 0.0,
            "final_loss": self.last_loss,
            "stopped_by_time_limit": timed_out,
        }

    def _out_of_time(self, now: float) -> bool:
        """Whether the time limit is reached; every rank of a ``torchrun`` group takes rank 0's word,
        so that they stop at the same step."""
        if self.deadline is None:
            return False
        return self.place.mean(float(now >= self.deadline) if self.place.is_main else 0.0) > 0


def _to_cpu(state: object) -> object:
    """``state`` (nested dicts/lists of tensors) with every tensor copied to the CPU."""
    if isinstance(state, torch.Tensor):
        return state.detach().cpu()
    if isinstance(state, dict):
        return {k: _to_cpu(v) for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(_to_cpu(v) for v in state)
    return state
