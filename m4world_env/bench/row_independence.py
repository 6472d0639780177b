"""Which ops of a batched world-model step are not row-independent on CPU?

    m4world bench row_independence [--checkpoint BUNDLE] [--rows 3] [--threads 1]
        [--dtype auto|float32|bfloat16] [--no-split] [--time ROUNDS] [--out F.json]

Runs a vector env of ``--rows`` world-model envs for two steps with a hook on every leaf module of
the student and the VAE and on the attention function: each call is repeated on each row's block
of its operands alone (dim 0 cut into ``--rows`` blocks, as :mod:`world_model.model.rows` does),
and the largest difference from the batched call's block is reported per module and shape. With
the default :func:`~world_model.model.rows.split_rows` in place every difference is 0;
``--no-split`` shows what it fixes. ``--time ROUNDS`` also reports what splitting costs: the
median vector step and vector reset (all rows) with and without it, in interleaved rounds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from contextlib import ExitStack, nullcontext
from unittest import mock

import gymnasium as gym
import numpy as np
import torch

import m4world_env  # noqa: F401
import world_model.model.attention as attention_module
import world_model.rollout.batch as batch
import world_model.rollout.runtime as runtime


def measure(checkpoint: str | None, rows: int, dtype: str, split: bool) -> dict[str, float]:
    stats: dict[str, float] = {}

    def record(key: str, batched: torch.Tensor, alone: list[torch.Tensor]) -> None:
        diff = max(float((a.float() - b.float()).abs().max()) for a, b in zip(alone, batched.chunk(rows), strict=True))
        stats[key] = max(stats.get(key, 0.0), diff)

    def hook(name: str) -> Callable[[torch.nn.Module, tuple, object], None]:
        def after(module: torch.nn.Module, inputs: tuple, output: object) -> None:
            x = inputs[0] if len(inputs) == 1 else None
            if not isinstance(x, torch.Tensor) or not isinstance(output, torch.Tensor) or output.numel() == 0:
                return
            if x.shape[0] % rows or x.shape[0] < rows:
                return
            with torch.no_grad(), torch._C.DisableTorchFunction():  # the reference call: unsplit
                record(f"{name} {type(module).__name__} {tuple(x.shape)}", output, [module(b) for b in x.chunk(rows)])

        return after

    original = attention_module.attention

    def attention(q, k, v, mask=None, scale=None):  # noqa: ANN001, ANN202 (the wrapped function's signature)
        out = original(q, k, v, mask, scale)
        if q.numel() and q.shape[0] % rows == 0 and q.shape[0] >= rows:
            per_row = mask is not None and mask.ndim == 4 and mask.shape[0] == q.shape[0]
            masks = mask.chunk(rows) if per_row else [mask] * rows
            with torch._C.DisableTorchFunction():
                alone = [
                    original(*t, m, scale)
                    for *t, m in zip(q.chunk(rows), k.chunk(rows), v.chunk(rows), masks, strict=True)
                ]
            record(f"attention {tuple(q.shape)} x {tuple(k.shape)}", out, alone)
        return out

    config = {"observation_keys": ["cameras", "lidar"], "model": {"dtype": dtype}}
    venv = gym.make_vec(
        "M4World-v0", num_envs=rows, vectorization_mode="vector_entry_point", scenario="merge_cut_in",
        backend="world_model", checkpoint=checkpoint, config=config,
    )  # fmt: skip
    wm = venv.unwrapped.backend.wm
    for root, model in (("vae", wm.vae), ("student", wm.student)):
        for name, module in model.named_modules():
            if not list(module.children()):
                module.register_forward_hook(hook(f"{root}.{name}"))
    no_split = mock.patch.object(batch.RolloutBatch, "_row_independent", lambda self: nullcontext())
    with mock.patch.object(attention_module, "attention", attention), no_split if not split else nullcontext():
        venv.reset(seed=5)
        for _ in range(2):
            venv.step(np.zeros((rows, 2), np.float32))
    return stats


def time_split(checkpoint: str | None, rows: int, dtype: str, rounds: int) -> dict[str, float]:
    """Median seconds of a vector step and of a vector reset with and without
    :func:`~world_model.model.rows.split_rows`, in interleaved rounds (the machine's speed drifts)."""
    config = {"observation_keys": ["cameras", "lidar"], "model": {"dtype": dtype}}
    venv = gym.make_vec(
        "M4World-v0", num_envs=rows, vectorization_mode="vector_entry_point", scenario="highway_sunny_day",
        backend="world_model", checkpoint=checkpoint, config=config,
    )  # fmt: skip

    def unsplit() -> ExitStack:  # the split of the batched steps and of the batched first frames, both off
        stack = ExitStack()
        for module in (batch, runtime):
            stack.enter_context(mock.patch.object(module, "split_rows", lambda n: nullcontext()))
        return stack

    times: dict[str, list[float]] = {k: [] for k in ("step_split", "step_unsplit", "reset_split", "reset_unsplit")}
    venv.reset(seed=0)
    venv.step(np.zeros((rows, 2), np.float32))  # warm-up
    for r in range(rounds):
        for mode in ("split", "unsplit") if r % 2 == 0 else ("unsplit", "split"):
            with unsplit() if mode == "unsplit" else nullcontext():
                t0 = time.perf_counter()
                venv.step(np.zeros((rows, 2), np.float32))
                t1 = time.perf_counter()
                venv.reset(seed=r)
                times[f"step_{mode}"].append(t1 - t0)
                times[f"reset_{mode}"].append(time.perf_counter() - t1)
    out = {f"{k}_s": statistics.median(v) for k, v in times.items()}
    out["step_cost"] = out["step_split_s"] / out["step_unsplit_s"] - 1.0
    out["reset_cost"] = out["reset_split_s"] / out["reset_unsplit_s"] - 1.0
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench row_independence", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=None, help="bundle folder (default: the shipped one)")
    p.add_argument("--rows", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--dtype", default="auto", choices=["auto", "float32", "bfloat16"])
    p.add_argument("--no-split", action="store_true", help="batched calls as they are, without split_rows")
    p.add_argument(
        "--time", type=int, default=0, metavar="ROUNDS", help="also time steps and resets with and without splitting"
    )
    p.add_argument("--out", default=None, help="write the figures as JSON")
    args = p.parse_args(argv)
    if args.rows < 2:
        p.error(f"--rows must be >= 2 to compare rows, got {args.rows}")
    torch.set_num_threads(args.threads)
    stats = measure(args.checkpoint, args.rows, args.dtype, not args.no_split)
    differing = {k: v for k, v in sorted(stats.items(), key=lambda kv: -kv[1]) if v > 0}
    for key, diff in differing.items():
        print(f"{diff:.3g}  {key}")
    print(f"{len(stats)} module/shape pairs checked, {len(differing)} not row-independent")
    result = {"args": vars(args), "checked": len(stats), "differing": differing}
    if args.time:
        result["timing"] = time_split(args.checkpoint, args.rows, args.dtype, args.time)
        print(json.dumps(result["timing"], indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
