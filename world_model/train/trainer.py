"""The training loop every stage shares: resume, step, EMA, progress, checkpoints, NaN guard.

Progress goes to a tqdm bar and, for background jobs without a terminal, to
``<stage_dir>/progress.json`` (step, total, loss, throughput, ETA), rewritten atomically at most
every ``PROGRESS_PERIOD_S`` seconds and at every checkpoint: ``cat`` it to follow a run.

Determinism: all randomness of a stage (data sampling, noise, timesteps, condition dropout) comes
from one ``numpy.random.Generator`` and one ``torch.Generator`` owned by the :class:`Trainer`;
both are checkpointed, so a run killed and restarted continues exactly as if uninterrupted.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from world_model.data.clips import write_json_atomic
from world_model.train.checkpoint import load_latest, save_checkpoint
from world_model.train.ema import EMA

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


class Trainer:
    def __init__(
        self,
        stage_dir: Path,
        model: nn.Module,
        tcfg: TrainConfig,
        meta: dict,
        progress: bool = True,
        resume_keys: dict[str, object] | None = None,
    ):
        """``resume_keys``: entries of ``meta`` a resumed run must share with its checkpoint (a
        setting that changes the objective mid-run), else :meth:`resume` raises ``ValueError``; each
        maps to the value meant by a checkpoint written before the entry existed."""
        self.resume_keys = dict(resume_keys or {})
        self.dir = Path(stage_dir)
        self.ckpt_dir = self.dir / "checkpoints"
        self.model = model
        self.tcfg = tcfg
        self.meta = meta
        self.progress = progress
        self.opt = torch.optim.AdamW(model.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)
        self.ema = EMA(model, tcfg.ema_decay)
        self.rng = np.random.default_rng(tcfg.seed)
        self.gen = torch.Generator().manual_seed(tcfg.seed)
        self.step = 0
        self.last_loss = float("nan")
        self.resumed_from: int | None = None

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
        self.gen.set_state(ck.train_state["torch_rng"])
        self.rng.bit_generator.state = ck.meta["numpy_rng"]
        self.step = ck.step
        self.last_loss = float(ck.meta.get("loss", float("nan")))
        self.resumed_from = ck.step
        return True

    def save(self) -> Path:
        meta = {
            **self.meta,
            "numpy_rng": self.rng.bit_generator.state,
            "ema_updates": self.ema.updates,
            "loss": self.last_loss,
            "train_config": asdict(self.tcfg),
        }
        return save_checkpoint(
            self.ckpt_dir,
            self.step,
            {"model": self.model.state_dict(), "ema": self.ema.state_dict()},
            {"optimizer": self.opt.state_dict(), "torch_rng": self.gen.get_state()},
            meta,
            keep=self.tcfg.keep_checkpoints,
        )

    def write_progress(self, desc: str, losses: list[float], rate_steps: float, rate_samples: float) -> None:
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
        """Train until ``tcfg.steps``; returns a summary (losses, throughput, resume point)."""
        self.resume()
        self.model.train()
        losses: list[float] = []
        samples, t0 = 0, time.perf_counter()
        last_report = t0
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
                value = float(loss.detach())
                if not math.isfinite(value):
                    raise TrainingDivergedError(
                        f"{desc}: loss is {value} at step {self.step + 1}; the last good checkpoint "
                        f"(if any) is kept in {self.ckpt_dir}. "
                        "Lower the learning rate or check the data, then rerun the same command to resume."
                    )
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                if self.tcfg.grad_clip > 0:
                    nn.utils.clip_grad_norm_(self.model.parameters(), self.tcfg.grad_clip)
                self.opt.step()
                self.ema.update(self.model)
                self.step += 1
                self.last_loss = value
                losses.append(value)
                samples += n
                now = time.perf_counter()
                rate = samples / max(now - t0, 1e-9)
                bar.set_postfix(loss=f"{value:.4f}", samples_per_s=f"{rate:.1f}")
                bar.update(1)
                checkpoint = self.step % self.tcfg.ckpt_every == 0 or self.step == self.tcfg.steps
                if checkpoint:
                    self.save()
                if checkpoint or now - last_report >= PROGRESS_PERIOD_S:
                    self.write_progress(desc, losses, len(losses) / max(now - t0, 1e-9), rate)
                    last_report = now
        finally:
            bar.close()
        elapsed = time.perf_counter() - t0
        return {
            "step": self.step,
            "losses": losses,
            "resumed_from": self.resumed_from,
            "samples_per_s": samples / elapsed if losses else 0.0,
            "final_loss": self.last_loss,
        }
