"""Causal student benchmark (random weights: timing and memory only), medians of one run.

The student has ``dit.student_depth`` blocks, the teacher ``dit.depth`` (the preset's).

1. ``student_vs_teacher``: one chunk (``clip.chunk_frames`` frames) for ``--envs`` rollouts: the
   4-step student's engine step (4 denoising forwards + 1 cache write, with context refresh over a
   full window of ``clip.context_frames`` cached frames) vs the bidirectional teacher sampling
   with ``sampler.steps`` guided Euler steps (CFG + APG: doubled batch), (a) in context: the
   teacher has no cache (its attention is bidirectional), so continuing a rollout means sampling
   the window + chunk jointly, ``context_frames + chunk_frames`` frames per step; (b) the chunk
   alone, no context: a lower bound that no streaming teacher achieves. Teacher samples are long
   (tens of forwards), so they are timed without a warm-up run.
2. ``cache_vs_recompute``: the engine with its KV cache vs recomputing the whole window at every
   denoising step (:class:`RecomputeWindow`, the computation the cache replaces), window full, with
   context refresh at every step, at the last two only, or off; all timed in interleaved rounds.
3. ``rollout``: a ``--frames`` long rollout (``--rollout-envs`` rows): per-chunk latency, process
   RSS along the way, cache bytes; memory growth from frame 100 to the end.
4. ``compiled_vs_eager`` (only when named in ``--sections``; inductor needs a C++ compiler): one
   cached chunk eager vs compiled, interleaved rounds.

    m4world bench student [--preset default] [--envs 8] [--frames 600] --out FILE.json
    m4world bench student --sections cache_vs_recompute --window 12 --out FILE.json

``--window`` overrides ``clip.context_frames`` (how the cache's advantage scales with the window);
``--student-depth`` overrides ``dit.student_depth`` (a shallower student than the preset's);
``--compile`` times the student compiled (the teacher stays eager); ``--device`` runs it all on
another device (default cpu; ``auto``: CUDA when available).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from m4world_env.bench.model import synthetic_conditions
from world_model.model import MultiViewDiT, get_preset, sample_latents
from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig, with_student_settings
from world_model.model.flow import gaussian, predict_x0
from world_model.precision import DTYPES, resolve_bf16, resolve_device
from world_model.student import StreamingEngine, StudentConfig, cat_frames, few_step_sample, rollout_blocks
from world_model.student.config import TRAINING_STREAMING

RSS_FROM_FRAME = 100  # memory growth is measured from here (window full, allocator warm)


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("VmRSS not found in /proc/self/status")


def timed(fn: Callable[[], object], repeats: int, warmup: int = 1) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def make_model(cfg: ModelConfig, device: torch.device) -> MultiViewDiT:
    torch.manual_seed(0)
    model = MultiViewDiT(cfg).eval()
    with torch.no_grad():  # adaLN-zero starts at zero: random weights make every path compute
        for p in model.parameters():
            p.normal_(0.0, 0.02)
    model = model.to(device)
    return model.to(torch.bfloat16) if cfg.dit.autocast_bf16 else model  # bf16 weights, as the env runs


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued kernels, so a timer measures them."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class RecomputeWindow:
    """The baseline the KV cache replaces: every denoising step re-runs the window's clean frames
    together with the noisy chunk in one block-causal forward; nothing is cached. Same interface
    as :class:`StreamingEngine` for :func:`warm_engine` (no context refresh, no sink frames)."""

    def __init__(self, model: MultiViewDiT, scfg: StudentConfig, generator: torch.Generator) -> None:
        self.model, self.scfg, self.gen, self.times = model, scfg, generator, scfg.times()
        self.position = self.prefix = 0
        self.history: torch.Tensor | None = None
        self.controls: Conditions | None = None

    def start(self, first: torch.Tensor, controls: Conditions) -> None:
        dev = next(self.model.parameters()).device
        self.history, self.controls = first.to(dev), controls.to(dev)
        self.position = self.prefix = first.shape[1]

    @torch.no_grad()
    def step(self, controls: Conditions) -> torch.Tensor:
        m, cfg = self.model, self.model.cfg
        c, hist = cfg.clip.chunk_frames, self.history
        f, dev = hist.shape[1], hist.device
        both = cat_frames(self.controls, controls.to(dev))
        tokens = m.tokenize(both)
        blocks = rollout_blocks(self.position - f, f + c, self.prefix, c)

        def recompute(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            tt = torch.cat([torch.ones(x.shape[0], f, device=dev), t[:, None].expand(-1, c)], dim=1)
            v = m(torch.cat([hist, x], 1), tt, tokens, causal=True, frame_offset=self.position - f, blocks=blocks)
            return predict_x0(x, v[:, f:], t)

        noise = gaussian((hist.shape[0], *cfg.latent_shape(c)), self.gen, dev)
        x0 = few_step_sample(recompute, noise, self.times, self.scfg.renoise, generator=self.gen)
        keep = min(cfg.clip.context_frames, f + c)
        self.history = torch.cat([hist, x0], 1)[:, -keep:]
        self.controls = both.frames(both.num_frames - keep, both.num_frames)
        self.position += c
        return x0


def warm_engine(
    model: MultiViewDiT, scfg: StudentConfig, envs: int, engine: type = StreamingEngine
) -> tuple[StreamingEngine, Callable[[], object]]:
    """An engine whose window is full, and a closure running one more chunk (and waiting for it)."""
    cfg = model.cfg
    c, w = cfg.clip.chunk_frames, cfg.clip.context_frames
    device = next(model.parameters()).device
    cond = synthetic_conditions(cfg, 1 + c, envs)
    eng = engine(model, scfg, torch.Generator().manual_seed(0))
    eng.start(torch.zeros(envs, *cfg.latent_shape(1)), cond.frames(0, 1))
    chunk = cond.frames(1, 1 + c)
    while eng.position < w + c:
        eng.step(chunk)

    def one_chunk() -> None:
        eng.step(chunk)
        synchronize(device)

    return eng, one_chunk


@torch.no_grad()
def student_vs_teacher(student: MultiViewDiT, teacher: MultiViewDiT, envs: int, repeats: int) -> dict:
    cfg = teacher.cfg
    _, step = warm_engine(student, StudentConfig(), envs)
    s = statistics.median(timed(step, repeats))
    out = {
        "envs": envs,
        "student_depth": student.cfg.dit.depth,
        "teacher_depth": cfg.dit.depth,
        "chunk_frames": cfg.clip.chunk_frames,
        "context_frames": cfg.clip.context_frames,
        "student_steps": StudentConfig().num_steps,
        "teacher_steps": cfg.sampler.steps,
        "student_chunk_s": s,
    }
    gen = torch.Generator().manual_seed(0)
    device = next(teacher.parameters()).device

    def sample(cond: Conditions) -> None:
        sample_latents(teacher, cond, gen)
        synchronize(device)

    for name, frames in (
        ("in_context", cfg.clip.context_frames + cfg.clip.chunk_frames),
        ("alone", cfg.clip.chunk_frames),
    ):
        cond = synthetic_conditions(cfg, frames, envs)
        t = statistics.median(timed(lambda cond=cond: sample(cond), max(1, repeats // 2), 0))
        out[f"teacher_{name}_chunk_s"] = t
        out[f"teacher_{name}_over_student"] = t / s
    return out


def interleaved(steps: dict[str, Callable[[], object]], repeats: int) -> dict:
    """Time each warmed step once per round, ``repeats`` rounds: ``<name>_chunk_s`` medians and
    ``<name>_rounds_s``. A drift of the shared machine's speed hits every step alike."""
    times: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            times[name] += timed(step, 1, warmup=0)
    out: dict = {}
    for name, t in times.items():
        out[f"{name}_chunk_s"] = statistics.median(t)
        out[f"{name}_rounds_s"] = t
    return out


@torch.no_grad()
def compiled_vs_eager(model: MultiViewDiT, envs: int, repeats: int) -> dict:
    """One cached chunk (refresh on) of the eager student and of the student compiled
    (``compile_blocks()``, what the env's ``compile`` option runs), in interleaved rounds; the
    compiled copy compiles during its warm-up chunks."""
    compiled = copy.deepcopy(model).requires_grad_(False)
    compiled.compile_blocks()
    steps = {
        name: warm_engine(m, StudentConfig(), envs)[1] for name, m in {"eager": model, "compiled": compiled}.items()
    }
    out = {"envs": envs, "window": model.cfg.clip.context_frames} | interleaved(steps, repeats)
    out["eager_over_compiled"] = out["eager_chunk_s"] / out["compiled_chunk_s"]
    return out


@torch.no_grad()
def cache_vs_recompute(model: MultiViewDiT, envs: int, repeats: int) -> dict:
    """The engines warmed first, then timed in interleaved rounds (one chunk each per round), so
    a drift of the shared machine's speed hits all alike. ``cached_refresh_late``: the context
    frame refreshed at the last two denoising steps only (``refresh_steps``)."""
    out = {"envs": envs, "window": model.cfg.clip.context_frames}
    no_refresh = StudentConfig(streaming=dataclasses.replace(TRAINING_STREAMING, context_refresh=False))
    configs = {
        "cached_refresh": StudentConfig(),
        "cached_refresh_late": StudentConfig(streaming=dataclasses.replace(TRAINING_STREAMING, refresh_steps=(-2, -1))),
        "cached_no_refresh": no_refresh,
    }
    steps = {name: warm_engine(model, scfg, envs)[1] for name, scfg in configs.items()}
    steps["recompute"] = warm_engine(model, no_refresh, envs, RecomputeWindow)[1]
    out |= interleaved(steps, repeats)
    for name in configs:
        if name != "recompute":
            out[f"recompute_over_{name}"] = out["recompute_chunk_s"] / out[f"{name}_chunk_s"]
    return out


@torch.no_grad()
def rollout(model: MultiViewDiT, envs: int, frames: int) -> dict:
    cfg = model.cfg
    c = cfg.clip.chunk_frames
    cond = synthetic_conditions(cfg, 1 + c, envs)
    eng = StreamingEngine(model, StudentConfig(), torch.Generator().manual_seed(0))
    eng.start(torch.zeros(envs, *cfg.latent_shape(1)), cond.frames(0, 1))
    chunk = cond.frames(1, 1 + c)
    first = min(RSS_FROM_FRAME, frames // 2)  # short smoke runs measure from half way
    times, rss, cache_bytes = [], {}, set()
    device = next(model.parameters()).device
    while eng.position + c <= frames:
        t0 = time.perf_counter()
        eng.step(chunk)
        synchronize(device)
        times.append(time.perf_counter() - t0)
        rss[eng.position] = rss_mb()
        if eng.position >= first:
            cache_bytes.add(eng.cache.nbytes())
    start, end = min(p for p in rss if p >= first), max(rss)
    report = {p: v for p, v in rss.items() if p % 50 < c or p in (start, end)}
    return {
        "envs": envs,
        "frames": eng.position,
        "chunk_latency_median_s": statistics.median(times),
        "chunk_latency_p90_s": sorted(times)[int(0.9 * (len(times) - 1))],
        "rss_mb_by_frame": report,
        "rss_growth_pct": 100.0 * (rss[end] - rss[start]) / rss[start],
        "rss_growth_from_frame": start,
        "cache_bytes_from_that_frame": sorted(cache_bytes),
    }


SECTIONS = {"student_vs_teacher": student_vs_teacher, "cache_vs_recompute": cache_vs_recompute, "rollout": rollout}
OPTIONAL_SECTIONS = {"compiled_vs_eager": compiled_vs_eager}  # needs a C++ compiler (inductor): only when asked


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="m4world bench student", description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="default")
    p.add_argument("--envs", type=int, default=8, help="batched rollouts for the speed comparisons")
    p.add_argument("--rollout-envs", type=int, default=1, help="rows of the long rollout")
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--window", type=int, default=None, help="override clip.context_frames")
    p.add_argument("--student-depth", type=int, default=None, help="override dit.student_depth")
    p.add_argument(
        "--compile",
        action="store_true",
        help="torch.compile the student's blocks (MultiViewDiT.compile_blocks), as the env's "
        "config={'model': {'compile': True}}; the warm-up chunks compile, the timed ones do not",
    )
    p.add_argument(
        "--dtype",
        default="auto",
        choices=DTYPES,
        help="the DiTs' precision, as the env's config={'model': {'dtype': ...}} (auto: bf16 only "
        "where the device multiplies it faster than float32)",
    )
    p.add_argument("--device", default="cpu", help="cpu, cuda[:N] or auto (CUDA when available)")
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=[*SECTIONS, *OPTIONAL_SECTIONS])
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    try:
        device = resolve_device(a.device)
    except ValueError as e:
        p.error(str(e))
    if a.compile and "compiled_vs_eager" in a.sections:
        p.error("compiled_vs_eager compiles its own copies: leave out --compile")
    if a.threads:
        torch.set_num_threads(a.threads)
    cfg = with_student_settings(get_preset(a.preset), a.student_depth, a.window)
    bf16 = resolve_bf16(a.dtype, cfg.dit.autocast_bf16, device)
    cfg = dataclasses.replace(cfg, dit=dataclasses.replace(cfg.dit, autocast_bf16=bf16))
    student = make_model(cfg.for_student(), device)
    if a.compile:
        student.requires_grad_(False).compile_blocks()
    result = {
        "preset": a.preset,
        "threads": torch.get_num_threads(),
        "compiled": a.compile,
        "device": str(device),
        "dit_dtype": "bfloat16" if bf16 else "float32",
        "model_config": {
            "clip": dataclasses.asdict(cfg.clip),
            "sampler_steps": cfg.sampler.steps,
            "teacher_depth": cfg.dit.depth,
            "student_depth": student.cfg.dit.depth,
        },
    }
    for name in a.sections:
        if name == "student_vs_teacher":
            result[name] = student_vs_teacher(student, make_model(cfg, device), a.envs, a.repeats)
        elif name == "rollout":
            result[name] = rollout(student, a.rollout_envs, a.frames)
        elif name == "compiled_vs_eager":
            result[name] = compiled_vs_eager(student, a.envs, a.repeats)
        else:
            result[name] = cache_vs_recompute(student, a.envs, a.repeats)
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "rollout"}, indent=1))
    if "rollout" in result:
        r = result["rollout"]
        print(
            f"rollout: {r['frames']} frames, chunk latency median {r['chunk_latency_median_s']:.3f}s, "
            f"RSS growth {r['rss_growth_pct']:.2f}% from frame {r['rss_growth_from_frame']}"
        )


if __name__ == "__main__":
    main()
