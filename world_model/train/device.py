"""Where a training process runs: its device (``--device auto|cpu|cuda[:N]``) and, under
``torchrun``, its place in the process group.

Multi-process training is data parallel: every rank draws the *global* batch from the same seeded
stream (numpy and torch generators seeded alike), keeps its own contiguous shard of the rows
(:meth:`TrainPlace.shard`) and averages its gradients with the other ranks after each backward
pass, so N processes at a global batch B take the same steps as one process at batch B (up to
float reduction order). Rank 0 alone writes checkpoints, exports, progress and logs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TypeVar

import torch
from torch import nn

DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"
T = TypeVar("T")


def resolve_device(spec: str) -> torch.device:
    """``auto`` (CUDA when this torch sees a GPU, else the CPU), ``cpu``, ``cuda`` or ``cuda:N``;
    a ``ValueError`` naming the option when the device is not there."""
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(spec)
    except RuntimeError:
        raise ValueError(f"--device must be {DEVICE_CHOICES}, got {spec!r}") from None
    if device.type == "cpu" and device.index is None:
        return device
    if device.type != "cuda":
        raise ValueError(f"--device must be {DEVICE_CHOICES}, got {spec!r}")
    if not torch.cuda.is_available():
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        raise ValueError(
            f"--device {spec}: no CUDA GPU is available to this torch ({torch.__version__}, {build}); "
            "install a CUDA build of torch on a machine with a GPU, or use --device cpu (or auto)"
        )
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise ValueError(f"--device {spec}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return device


@dataclass(frozen=True)
class TrainPlace:
    """One training process: its device, rank and the number of ranks (1 without ``torchrun``)."""

    device: torch.device
    rank: int = 0
    world_size: int = 1

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """The rank that writes checkpoints, exports, progress and logs."""
        return self.rank == 0

    def local_rows(self, batch: int) -> slice:
        """This rank's contiguous rows of a global batch of ``batch`` rows."""
        if batch % self.world_size:
            raise ValueError(
                f"the batch size ({batch}) must be a multiple of the number of processes ({self.world_size}): "
                "each rank trains an equal shard of the global batch"
            )
        n = batch // self.world_size
        return slice(self.rank * n, (self.rank + 1) * n)

    def shard(self, x: T) -> T:
        """This rank's rows of ``x`` (a tensor or :class:`~world_model.model.conditions.Conditions`)
        of the global batch, on this process's device."""
        if isinstance(x, torch.Tensor):
            return self._move(x[self.local_rows(x.shape[0])] if self.distributed else x)
        rows = self.local_rows(x.batch_size) if self.distributed else slice(None)  # type: ignore[attr-defined]
        return x.apply(lambda _, v: self._move(v[rows]))  # type: ignore[attr-defined]

    def _move(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` on this device; a CPU batch bound for a GPU goes through pinned memory, copied
        asynchronously."""
        if x.device == self.device:
            return x
        if self.device.type == "cuda" and x.device.type == "cpu":
            return x.pin_memory().to(self.device, non_blocking=True)
        return x.to(self.device)

    def average_gradients(self, module: nn.Module) -> None:
        """Average the gradients of ``module`` over the ranks (one flat all-reduce)."""
        if not self.distributed:
            return
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        if not grads:
            return
        flat = torch.cat([g.reshape(-1) for g in grads])
        torch.distributed.all_reduce(flat)
        flat /= self.world_size
        offset = 0
        for g in grads:
            g.copy_(flat[offset : offset + g.numel()].view_as(g))
            offset += g.numel()

    def mean(self, value: float) -> float:
        """``value`` averaged over the ranks (the logged loss of the global batch)."""
        if not self.distributed:
            return value
        t = torch.tensor([value], dtype=torch.float64, device=self.device)
        torch.distributed.all_reduce(t)
        return float(t) / self.world_size

    def barrier(self) -> None:
        if self.distributed:
            torch.distributed.barrier(**({"device_ids": [self.device.index]} if self.device.type == "cuda" else {}))


def launched_by_torchrun() -> bool:
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init_place(device: str) -> TrainPlace:
    """This process's :class:`TrainPlace`; under ``torchrun`` (``WORLD_SIZE`` > 1) it joins the
    process group: nccl on CUDA (each rank on ``cuda:LOCAL_RANK``), gloo on the CPU."""
    if not launched_by_torchrun():
        return TrainPlace(resolve_device(device))
    import torch.distributed as dist

    rank, world, local = (int(os.environ[k]) for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK"))
    dev = resolve_device(device)
    if dev.type == "cuda":
        dev = torch.device("cuda", local)
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo", rank=rank, world_size=world)
    return TrainPlace(dev, rank, world)


def close_place(place: TrainPlace) -> None:
    """Leave the process group (a no-op for one process)."""
    if place.distributed and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
