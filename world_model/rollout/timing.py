"""Where a rollout's time goes: an optional timer the pipeline reports its stages to.

The pipeline's parts (:class:`~world_model.rollout.conditions.RolloutConditions`,
:class:`~world_model.rollout.batch.RolloutBatch`) time their stages only when a
:class:`StageTimer` is attached to them (their ``timer``, None by default): the env runs without
one, so it reads no clock and waits for no device; the benchmarks attach one
(``m4world bench env``'s split of a step, the simulation workers' ``seconds``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext

import torch

# The stages of a step: cutting reference crops and building condition arrays (CPU), the
# student's chunk, the VAE decoder.
PIPELINE_STAGES = ("crops", "conditions", "student", "decode")


class StageTimer:
    """Wall seconds per stage of :data:`PIPELINE_STAGES`, summed over the calls timed so far."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(PIPELINE_STAGES, 0.0)

    @contextmanager
    def stage(self, name: str, device: torch.device | None = None) -> Iterator[None]:
        """Time the block as stage ``name``. With a CUDA ``device`` the clock stops once its queued
        kernels finished, so asynchronous work counts to the stage that queued it, not to the next
        one that reads its results."""
        if name not in self.seconds:
            raise KeyError(f"stage must be one of {PIPELINE_STAGES}, got {name!r}")
        start = time.perf_counter()
        yield
        if device is not None and device.type == "cuda":
            torch.cuda.synchronize(device)
        self.seconds[name] += time.perf_counter() - start


def timed(timer: StageTimer | None, name: str, device: torch.device | None = None) -> AbstractContextManager:
    """``timer.stage(name, device)``, or nothing at all without a timer."""
    return nullcontext() if timer is None else timer.stage(name, device)
