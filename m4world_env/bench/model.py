"""World-model core benchmark: parameters, analytic FLOPs, DiT forward speed vs the CPU's matmul peak.

One causal chunk of the gym env = ``clip.chunk_frames`` new frames for 8 batched envs x all views,
attending to ``clip.context_frames`` cached frames: the denoising forwards of the shipped bundle's
streaming config (one frame longer where they refresh the context frame) + 1 cache-write forward
of the DiT, then VAE decoding of the newest frame (8 envs x views), as the env does
(:func:`chunk_forwards`; ``env_step_estimate_s``). This script
times one DiT forward and that decode the way the env runs them (``--dtypes auto``: bf16 weights
when ``dit.autocast_bf16`` and the CPU multiplies bf16 faster than float32; ``fp32``/``bf16`` force one);
``--compile`` adds rows with the blocks compiled (env ``config.model.compile``).
``--device`` times another device than the CPU (cuda[:N], or auto: CUDA when available; its
peak and rows alike). ``--heaps``: the process's allocator as the train CLIs set it on CPU (``retain``:
world_model.train.heap.retain_freed_memory) and/or glibc's ``default``; with both, each runs in its own
fresh process, alternating over ``--rounds`` rounds, and the rows give the medians (each row also
reports the minor page faults of one forward). It measures the machine's matmul peak in the same
run (a 4096^2 matmul, fp32 and bf16) and reports medians; each row's fraction of peak is against
the peak of its own dtype. ``--models``: the causal student the env runs (``dit.student_depth``
blocks, default) and/or the preset's full-depth teacher (``dit.depth``).

    m4world bench model [--presets tiny default] [--models student teacher]
        [--dtypes auto fp32 bf16] [--compile] [--heaps retain default] [--rounds 3] [--repeats 7]
        [--device cpu] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from world_model.bundle import DEFAULT_BUNDLE, read_streaming, streaming_config
from world_model.model import Conditions, HashTextEncoder, MultiViewDiT, SensorVAE, build_condition_arrays
from world_model.model.config import ModelConfig, get_preset
from world_model.model.flops import dit_forward_flops
from world_model.precision import resolve_bf16, resolve_device
from world_model.sim.demo import demo_frame, straight_road
from world_model.streaming import StreamingConfig
from world_model.train.heap import retain_freed_memory

ENVS = 8  # batched envs of one vector-env step
CACHE_FORWARDS = 1  # one forward on the clean chunk to write the KV cache
PEAK_SIZE = 4096
CPU = torch.device("cpu")
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
DEMO_EGO_STEP_M = 2.0  # the ego's advance per frame: 20 m/s at 10 Hz
HEAPS = ("retain", "default")  # world_model.train.heap.retain_freed_memory, or glibc's allocator as is
# Per-row numbers --heaps takes the median of over its rounds.
NUMBERS = (
    "forward_s",
    "achieved_gflops",
    "fraction_of_peak",
    "page_faults_per_forward",
    "vae_decode_s",
    "vae_decode_ms_per_frame",
    "env_step_estimate_s",
)


def median_time(fn: Callable[[], object], repeats: int, warmup: int = 2, device: torch.device | None = None) -> float:
    """Median wall time of ``fn``; on a CUDA ``device`` each call waits for its kernels."""

    def call() -> None:
        fn()
        if device is not None and device.type == "cuda":
            torch.cuda.synchronize(device)

    for _ in range(warmup):
        call()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def matmul_peak(dtype: torch.dtype, repeats: int, device: torch.device = CPU) -> float:
    a = torch.randn(PEAK_SIZE, PEAK_SIZE, dtype=dtype, device=device)
    b = torch.randn(PEAK_SIZE, PEAK_SIZE, dtype=dtype, device=device)
    return 2 * PEAK_SIZE**3 / median_time(lambda: a @ b, repeats, device=device) / 1e9


def row_dtype(cfg: ModelConfig, dtype_name: str, device: torch.device) -> str:
    """The precision a row of ``dtype_name`` runs in: "auto" as the env's dtype "auto" (bf16 only where
    the checkpoint was trained for it and the device multiplies it faster than float32)."""
    if dtype_name == "auto":
        return "bf16" if resolve_bf16("auto", cfg.dit.autocast_bf16, device) else "fp32"
    return dtype_name


def synthetic_conditions(cfg: ModelConfig, frames: int, batch: int) -> Conditions:
    """Conditions of a demo highway drive with a full object list; timing does not depend on their values."""
    rig, road, sensors = cfg.sensors.rig(), straight_road(), cfg.sensors
    scene = [
        replace(
            demo_frame(cfg.control.max_objects, rig=rig, road=road, frame_index=f, ego_x=DEMO_EGO_STEP_M * f),
            lidar=sensors.lidar,
            bev=sensors.bev,
        )
        for f in range(frames)
    ]
    bev = np.zeros((frames, *sensors.bev.shape), np.uint8)
    arr = build_condition_arrays(scene, bev, cfg, HashTextEncoder(cfg.text.dim))  # same widths as MiniLM
    return Conditions.collate([arr] * batch)


def chunk_forwards(streaming: StreamingConfig, chunk_frames: int) -> float:
    """The DiT forwards of one chunk, in forwards of ``chunk_frames`` frames: each denoising step,
    one frame longer where it refreshes the context frame, and the cache write. Attention grows
    a little faster than the frames: an estimate."""
    refreshed = len(streaming.resolved_refresh_steps())
    longer = (chunk_frames + 1) / chunk_frames
    return refreshed * longer + (streaming.denoising_steps - refreshed) + CACHE_FORWARDS


def shipped_streaming() -> StreamingConfig:
    """How the shipped bundle's student streams (its ``streaming.json``)."""
    return streaming_config(DEFAULT_BUNDLE, read_streaming(DEFAULT_BUNDLE))


@torch.no_grad()
def bench_config(
    cfg: ModelConfig,
    repeats: int,
    peaks: dict[str, float],
    dtype_name: str,
    compile_: bool,
    which: str = "student",
    device: torch.device = CPU,
) -> dict:
    torch.manual_seed(0)
    cfg = cfg.for_student() if which == "student" else cfg
    dtype_name = row_dtype(cfg, dtype_name, device)
    dtype = DTYPES[dtype_name]
    cfg = replace(cfg, dit=replace(cfg.dit, autocast_bf16=dtype_name == "bf16"))  # as runtime.load_world_model
    model = MultiViewDiT(cfg).eval().requires_grad_(False).to(device, dtype)  # as runtime.load_world_model
    if compile_:
        model.compile_blocks()
    vae = SensorVAE(cfg).eval().to(device, dtype)
    chunk, ctx = cfg.clip.chunk_frames, cfg.clip.context_frames
    n, v = cfg.tokens_per_frame, cfg.sensors.num_views
    tokens = model.tokenize(synthetic_conditions(cfg, chunk, ENVS).to(device))
    x = torch.randn(ENVS, *cfg.latent_shape(chunk), device=device)
    t = torch.full((ENVS,), 0.5, device=device)
    kv = [
        tuple(
            torch.randn(ENVS * v, cfg.dit.heads, ctx * n, cfg.dit.head_dim, dtype=dtype, device=device)
            for _ in range(2)
        )
        for _ in range(cfg.dit.depth)
    ]

    def forward() -> torch.Tensor:
        return model(x, t, tokens, causal=True, frame_offset=ctx, kv_context=kv)

    fwd = median_time(forward, repeats, warmup=3 if compile_ else 2, device=device)
    faults = []
    for _ in range(3):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        forward()
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    z = torch.randn(ENVS * v, cfg.vae.latent_channels, *cfg.latent_hw, dtype=dtype, device=device)  # newest frame
    dec = median_time(lambda: vae.decode(z), repeats, device=device)
    flops = dit_forward_flops(cfg, ENVS, chunk, ctx, cross_kv=False)  # tokens carry the cross K/V
    achieved = flops["total"] / fwd / 1e9
    return {
        "preset": cfg.name,
        "model": which,
        "depth": cfg.dit.depth,
        "dtype": dtype_name,
        "compiled": compile_,
        "device": str(device),
        "dit_params_m": sum(p.numel() for p in model.parameters()) / 1e6,
        "vae_params_m": sum(p.numel() for p in vae.parameters()) / 1e6,
        "tokens_per_forward": ENVS * v * chunk * n,
        "forward_gflop": flops["total"] / 1e9,
        "forward_linear_gflop": flops["linear"] / 1e9,
        "forward_s": fwd,
        "page_faults_per_forward": statistics.median(faults),
        "achieved_gflops": achieved,
        "fraction_of_peak": achieved / peaks[dtype_name],
        "vae_decode_s": dec,
        "vae_decode_ms_per_frame": 1e3 * dec / (ENVS * v),
        "env_step_estimate_s": chunk_forwards(shipped_streaming(), chunk) * fwd + dec,
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="m4world bench model", description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=["tiny", "default"])
    p.add_argument("--models", nargs="+", default=["student"], choices=["student", "teacher"])
    p.add_argument("--dtypes", nargs="+", default=["auto"], choices=["auto", *DTYPES], help="auto: as the env runs it")
    p.add_argument(
        "--compile", action="store_true", help="also rows with the DiT blocks torch.compile'd (needs a C++ compiler)"
    )
    p.add_argument(
        "--heaps",
        nargs="+",
        default=["retain"],
        choices=HEAPS,
        help="allocator: as the env sets it (retain), glibc's default",
    )
    p.add_argument("--rounds", type=int, default=3, help="with several --heaps: alternating fresh-process rounds")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--device", default="cpu", help="cpu, cuda[:N] or auto (CUDA when available)")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    a = p.parse_args(argv)
    try:
        resolve_device(a.device)
    except ValueError as e:
        p.error(str(e))
    result = compare_heaps(a) if len(a.heaps) > 1 else run_rows(a, a.heaps[0])
    print_rows(result)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(result, f, indent=1)


def run_rows(a: argparse.Namespace, heap: str) -> dict:
    """Every requested row in this process, with the allocator set up as ``heap``."""
    if heap == "retain":
        retain_freed_memory()
    device = resolve_device(a.device)
    # The peak of each precision the rows run in only: an emulated bf16 peak takes minutes.
    used = {row_dtype(get_preset(name), dtype, device) for name in a.presets for dtype in a.dtypes}
    peaks = {name: matmul_peak(DTYPES[name], a.repeats, device) for name in sorted(used)}
    rows = [
        {**bench_config(get_preset(name), a.repeats, peaks, dtype, compiled, which, device), "heap": heap}
        for name in a.presets
        for which in a.models
        for dtype in a.dtypes
        for compiled in ((False, True) if a.compile else (False,))
    ]
    return {
        "envs": ENVS,
        "threads": torch.get_num_threads(),
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "peak_gflops": peaks,
        "presets": rows,
    }


def compare_heaps(a: argparse.Namespace) -> dict:
    """Each heap setting in fresh processes (the allocator setting is process-wide and lasting),
    alternating over ``a.rounds`` rounds, merged by :func:`merge_heap_rounds`."""
    rounds = []
    for _ in range(a.rounds):
        one = {}
        for heap in a.heaps:
            cmd = [sys.executable, "-m", "m4world_env.bench.model", "--presets", *a.presets, "--models", *a.models]
            cmd += ["--dtypes", *a.dtypes, "--heaps", heap, "--repeats", str(a.repeats), "--device", a.device]
            cmd += ["--out", "/dev/stdout"] + (["--compile"] if a.compile else [])
            out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            one[heap] = json.loads(out[out.index("{") :])
        rounds.append(one)
    return merge_heap_rounds(rounds, a.heaps)


def merge_heap_rounds(rounds: list[dict[str, dict]], heaps: list[str]) -> dict:
    """Rounds of ``{heap: run_rows result}`` as one result: each row's :data:`NUMBERS` are their
    medians over the rounds, ``speedup_vs_default`` the median over rounds of the default heap's
    forward time over the row's within a round, the peaks the median over every run."""
    rows = []
    for heap in heaps:
        for i, row in enumerate(rounds[0][heap]["presets"]):
            merged = dict(row)
            for key in NUMBERS:
                merged[key] = statistics.median(r[heap]["presets"][i][key] for r in rounds)
            merged["speedup_vs_default"] = statistics.median(  # --heaps has both choices here
                r["default"]["presets"][i]["forward_s"] / r[heap]["presets"][i]["forward_s"] for r in rounds
            )
            rows.append(merged)
    measured = rounds[0][heaps[0]]["peak_gflops"]
    peaks = {k: statistics.median(r[h]["peak_gflops"][k] for r in rounds for h in heaps) for k in measured}
    return {
        "envs": ENVS,
        "threads": rounds[0][heaps[0]]["threads"],
        "peak_gflops": peaks,
        "presets": rows,
        "per_round": rounds,
    }


def print_rows(result: dict) -> None:
    peaks = result["peak_gflops"]
    measured = ", ".join(f"{name} {gflops:.0f} GFLOP/s" for name, gflops in peaks.items())
    print(f"matmul peak: {measured} ({result['threads']} threads)")
    rows = result["presets"]
    cols = [
        "preset",
        "model",
        "depth",
        "dtype",
        "compiled",
        "heap",
        "dit_params_m",
        "forward_gflop",
        "forward_s",
        "achieved_gflops",
        "fraction_of_peak",
        "page_faults_per_forward",
        "vae_decode_ms_per_frame",
        "env_step_estimate_s",
    ] + (["speedup_vs_default"] if "speedup_vs_default" in rows[0] else [])
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c]) for c in cols))


if __name__ == "__main__":
    main()
