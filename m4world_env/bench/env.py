"""Env steps/s for 1 and N envs per backend, next to highway-env's own envs, in one run.

    m4world bench env --out out/bench_env.json [--backend procedural]

Reports, per backend: one env's median step time and steps/s; a vector env of ``--num-envs``
(one batched backend call per step) vs the same number of single envs stepped one after another;
the split of a step into traffic (bridge) and sensor time; for the world-model backend the share
of the vector step spent outside the networks (traffic, condition building: BEV raster, text,
crops; everything but the student and the VAE decoder) and the vector step's split into traffic /
conditions / student / decode / other per env step; the time of a reset of one env and of the
vector env (every sub-env's first frame at once); the peak RSS of a process running one env
(a subprocess per backend). highway-v0 and highway-fast-v0 are measured in the same run. The
policy is the lane-keeping reference policy; its time is not counted.

The machine is shared and its speed drifts by 10-40 % over minutes, so the run is split into
``--rounds`` interleaved rounds (highway-env's envs, then each backend, again and again): every
ratio to highway-env is taken within one round, and the report gives the median over rounds of
each figure and each ratio (the rounds themselves under ``per_round``). Each backend's round runs
in a fresh process (``--no-isolate``: in this one), so the single-threaded procedural backend never
shares its process with the world model's torch threads or an earlier round's envs.

    m4world bench env --backend procedural world_model --out F.json [--checkpoint BUNDLE]

``--device`` runs the world-model backends there (``config.model.device``: cpu, cuda[:N], auto).

Simulation workers (``config.workers``, docs/scaling.md) instead of the backends:

    OMP_NUM_THREADS=1 m4world bench env --workers 0 2 --num-envs 64 --rounds 2 \
        --vector-steps 4 --out F.json [--compare-tree OTHER_CHECKOUT]

times one world-model vector env per worker count, each in a fresh process, in interleaved rounds
(:func:`bench_workers`), and reports the non-model throughput of each count over 0 workers' and
whether all of them observed the same (null when a single run compared nothing); ``--compare-tree``
adds 0 workers of another checkout's packages (e.g. ``git archive main | tar -x -C DIR``) to every
round.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.policies import ConstantSpeedLaneKeeping
from world_model.precision import DTYPES

CONFIG = {"observation_keys": ["cameras", "lidar"]}
PROC_STATUS = Path("/proc/self/status")
KB_PER_MB = 1024
# This module as a program again: the probes that time or measure one backend in a fresh process.
PROBE = [sys.executable, "-m", "m4world_env.bench.env"]
# This file run by path over another checkout's packages (--compare-tree): that checkout may have no
# m4world_env.bench, and nothing may come before its PYTHONPATH on sys.path (-c puts the cwd first).
RUN_FILE = (
    "import runpy, sys; del sys.path[0]; sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')"
)


def _time_single(env: gym.Env, steps: int, seed: int, warmup: int = 0) -> tuple[list[float], list[float]]:
    """Per-step wall times and the bridge's share of each, for one env (after ``warmup`` untimed steps)."""
    base = env.unwrapped
    env.reset(seed=seed)
    policy = ConstantSpeedLaneKeeping()
    totals, traffic = [], []
    for i in range(warmup + steps):
        action = policy(base.bridge)
        t0 = time.perf_counter()
        frames = base.advance(action)
        t1 = time.perf_counter()
        (observations,) = base.backend.step([frames])
        *_, terminated, truncated, _ = base.finish_step(frames, observations)
        t2 = time.perf_counter()
        if i >= warmup:
            totals.append(t2 - t0)
            traffic.append(t1 - t0)
        if terminated or truncated:
            env.reset(seed=seed)
            policy = ConstantSpeedLaneKeeping()
    return totals, traffic


# The qualifiers that set one count of config.model: name -> (config key, what N is).
COUNT_QUALIFIERS = {
    "threads": ("threads", "a thread count"),
    "rollout-threads": ("rollout_threads", "a number of rollout groups stepped at once"),
    "sink": ("sink_frames", "a number of frames"),
    "denoise": ("denoising_steps", "a number of denoising steps"),
    "first": ("first_frame_steps", "a number of first-frame steps"),
}


def make_kwargs(backend: str, checkpoint: str | None, compile_model: bool = False, device: str = "cpu") -> dict:
    """gym.make keywords for a backend spec: ``procedural``, or ``world_model`` with optional
    ``:``-separated qualifiers of its model options: a dtype (``world_model:bfloat16`` beside
    ``world_model``'s auto), ``compile`` (``config.model.compile``, as ``--compile`` does for every
    world-model backend) and/or ``no-refresh`` (``context_refresh`` off: the student's latent context
    refresh, §4.2, skipped) or ``refresh=K[,K...]`` (``refresh_steps``: refresh at those denoising
    steps only, e.g. ``refresh=0``; the env's default is the last two) or ``refresh=all``
    (``refresh_steps="all"``: every step, the paper's), ``sink=N`` (``sink_frames``: the first N
    frames kept in context beside the window), ``denoise=N`` (``denoising_steps``), ``first=N``
    (``first_frame_steps``: the reference model's steps at reset), ``one-step-first`` or
    ``no-one-step-first`` (``one_step_first_frame``: a reset's first frame in one step of the
    bundle's first-frame model, or in the reference model's steps), ``keys=K[+K...]``
    (``observation_keys``: e.g. ``keys=lidar`` decodes no camera), ``threads=N`` or ``threads=torch``
    (``config.model.threads``: N torch threads, or torch's own choice), ``rollout-threads=N``
    (``config.model.rollout_threads``: the vector env's rollouts in N groups on threads of their
    own), and ``checkpoint=BUNDLE`` (this backend's bundle instead of ``--checkpoint``'s: two
    checkpoints compared within one run's rounds). ``device``: ``config.model.device`` of the
    world-model backends."""
    name, *qualifiers = backend.split(":")
    kw = {"backend": name, "config": CONFIG}
    if name != "world_model":
        if qualifiers:
            raise SystemExit(f"only the world_model backend takes qualifiers, got {backend!r}")
        return kw
    model = {"compile": True} if compile_model else {}
    if device != "cpu":
        model["device"] = device
    for q in qualifiers:
        if q in DTYPES:
            model["dtype"] = q
        elif q == "compile":
            model["compile"] = True
        elif q == "no-refresh":
            model["context_refresh"] = False
        elif q in ("one-step-first", "no-one-step-first"):
            model["one_step_first_frame"] = q == "one-step-first"
        elif q.startswith("checkpoint="):
            checkpoint = q.removeprefix("checkpoint=")
            if not checkpoint:
                raise SystemExit(f"checkpoint=BUNDLE needs a bundle folder, got {backend!r}")
        elif q == "refresh=all":
            model["refresh_steps"] = "all"
        elif q.startswith("refresh="):
            try:
                model["refresh_steps"] = [int(k) for k in q.removeprefix("refresh=").split(",")]
            except ValueError:
                raise SystemExit(f"refresh=K[,K...] takes denoising-step indices, got {q!r} in {backend!r}") from None
        elif q == "threads=torch":
            model["threads"] = None  # torch's own choice: one thread per core
        elif q.split("=", 1)[0] in COUNT_QUALIFIERS and "=" in q:
            name, value = q.split("=", 1)
            key, what = COUNT_QUALIFIERS[name]
            try:
                model[key] = int(value)
            except ValueError:
                raise SystemExit(f"{name}=N takes {what}, got {q!r} in {backend!r}") from None
        elif q.startswith("keys="):
            kw["config"] = {**kw["config"], "observation_keys": q.removeprefix("keys=").split("+")}
        else:
            raise SystemExit(
                f"unknown qualifier {q!r} in {backend!r}: a dtype {DTYPES}, compile, no-refresh, "
                "refresh=K[,K...], refresh=all, sink=N, denoise=N, first=N, [no-]one-step-first, keys=K[+K...], "
                "threads=N|torch, "
                "rollout-threads=N or checkpoint=BUNDLE"
            )
    if checkpoint:
        kw["checkpoint"] = checkpoint
    if model:
        kw["config"] = {**kw["config"], "model": model}
    return kw


def peak_rss_one_env(
    backend: str, scenario: str, steps: int, seed: int, checkpoint: str | None, device: str = "cpu"
) -> float:
    """Peak RSS (MB) of a fresh process that makes one env and steps it ``steps`` times."""
    cmd = [*PROBE, "--memory-probe", backend, "--scenario", scenario, "--steps", str(steps)]
    cmd += ["--seed", str(seed), "--device", device, "--out", "-"]
    cmd += ["--checkpoint", checkpoint] if checkpoint else []
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return float(out.strip().splitlines()[-1])


def _memory_probe(backend: str, scenario: str, steps: int, seed: int, checkpoint: str | None, device: str) -> None:
    env = gym.make("M4World-v0", scenario=scenario, **make_kwargs(backend, checkpoint, device=device))
    _time_single(env, steps, seed)
    print(own_peak_rss_mb())


def status_peak_rss_mb(status: str) -> float | None:
    """The peak resident set (``VmHWM``, kB) of a ``/proc/PID/status`` text, in MB; None without one."""
    for line in status.splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / KB_PER_MB
    return None


def own_peak_rss_mb() -> float:
    """This process's peak RSS in MB. Not ``getrusage``: Linux keeps ``ru_maxrss`` across execve,
    so a probe started by a big parent would report the parent's peak; ``VmHWM`` belongs to the
    process's own address space, which execve replaces."""
    peak = status_peak_rss_mb(PROC_STATUS.read_text()) if PROC_STATUS.exists() else None
    return peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / KB_PER_MB  # upper bound


def _timed(fn, total: list[float]):  # noqa: ANN001, ANN202 (wraps any callable)
    """``fn`` adding its wall seconds to ``total[0]`` at each call."""

    def timed(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            total[0] += time.perf_counter() - t0

    return timed


@dataclass(frozen=True)
class BackendRun:
    """One backend's timed pass (:func:`bench_backend`), as the command line sets it: ``steps`` timed
    single-env steps and ``steps / num_envs`` (at least 10) timed vector steps of ``num_envs``
    sub-envs, each after ``warmup`` untimed ones (first calls allocate, torch.compile compiles);
    ``resets`` timed resets of the single env and of the vector env, each after one untimed; the
    world model's bundle, ``torch.compile`` and device (:func:`make_kwargs`)."""

    scenario: str
    steps: int
    num_envs: int
    seed: int
    checkpoint: str | None = None
    compile_model: bool = False
    warmup: int = 2
    device: str = "cpu"
    resets: int = 2

    @classmethod
    def from_args(cls, args: argparse.Namespace, steps: int, warmup: int) -> BackendRun:
        """The run the command line's flags ask for, at ``steps`` and ``warmup``."""
        return cls(args.scenario, steps, args.num_envs, args.seed, args.checkpoint, args.compile, warmup, args.device)


def bench_backend(backend: str, run: BackendRun) -> dict:
    """One backend's single-env and vector passes (:class:`BackendRun`). A vector step is split
    into traffic (the sub-envs' bridges), conditions (BEV raster, text, crops), student, decode and
    other (rewards, observations, Python), per env step."""
    kw = make_kwargs(backend, run.checkpoint, run.compile_model, run.device)
    single = gym.make("M4World-v0", scenario=run.scenario, **kw)
    totals, traffic = _time_single(single, run.steps, run.seed, run.warmup)
    step_s = statistics.median(totals)
    result = {
        "single_median_step_ms": 1e3 * step_s,
        "single_steps_per_s": 1.0 / step_s,
        "traffic_share": statistics.median(traffic) / step_s,
        "frames_per_step": single.unwrapped.scenario.frames_per_step,
    }
    venv = gym.make_vec(
        "M4World-v0",
        num_envs=run.num_envs,
        vectorization_mode="vector_entry_point",
        scenario=run.scenario,
        **kw,
    )
    result |= _time_resets(single, venv, run.seed, run.resets)
    single.close()
    rollouts = getattr(venv.unwrapped.backend, "rollouts", None)  # world-model backend only
    if rollouts is not None:  # what dtype "auto" chose on this machine
        result["dit_dtype"] = rollouts.wm.dtype
    vec_times, parts = _time_vector_steps(venv, run, with_model=rollouts is not None)
    result |= _vector_figures(vec_times, parts, run.num_envs, step_s, with_model=rollouts is not None)
    venv.close()
    del single, venv
    # Each round builds new envs (--no-isolate: in this process): collect the old ones now rather
    # than during a later round's timed steps.
    gc.collect()
    return result


def _time_resets(single: gym.Env, venv: gym.vector.VectorEnv, seed: int, resets: int) -> dict[str, float]:
    """The median of ``resets`` resets of the single env and of the vector env (all sub-envs at
    once), each after an untimed one; nothing at 0 resets."""
    single_resets, vector_resets = [], []
    for r in range(1 + resets):  # the first of each is warm-up (allocation, first text encodings)
        t0 = time.perf_counter()
        single.reset(seed=seed + r)
        t1 = time.perf_counter()
        venv.reset(seed=seed + r)
        if r:
            single_resets.append(t1 - t0)
            vector_resets.append(time.perf_counter() - t1)
    if not resets:
        return {}
    single_ms, vector_ms = 1e3 * statistics.median(single_resets), 1e3 * statistics.median(vector_resets)
    return {"single_reset_ms": single_ms, "vector_reset_ms": vector_ms, "vector_reset_vs_single": vector_ms / single_ms}


def _time_vector_steps(
    venv: gym.vector.VectorEnv, run: BackendRun, with_model: bool
) -> tuple[list[float], list[dict[str, float]]]:
    """The wall time of each timed vector step and its parts: traffic, then (``with_model``: the
    world-model backend) conditions, student and decode, and the rest as other."""
    traffic_s = [0.0]
    for env in venv.unwrapped.envs:  # the traffic half of each sub-env's step, timed in place
        env.advance = _timed(env.advance, traffic_s)
    stage_seconds = _stage_seconds_reader(venv.unwrapped.backend) if with_model else None

    def model_seconds() -> dict[str, float]:
        seconds = stage_seconds()
        seconds["conditions"] += seconds.pop("crops")
        return seconds

    policies = [ConstantSpeedLaneKeeping() for _ in range(run.num_envs)]
    vec_times, parts = [], []
    for i in range(run.warmup + max(run.steps // run.num_envs, 10)):
        actions = np.stack([p(e.bridge) for p, e in zip(policies, venv.unwrapped.envs, strict=True)])
        before = model_seconds() if with_model else {}
        traffic_s[0] = 0.0
        t0 = time.perf_counter()
        venv.step(actions)
        if i < run.warmup:
            continue
        vec_times.append(time.perf_counter() - t0)
        part = {"traffic": traffic_s[0]}
        if with_model:
            after = model_seconds()
            part.update({k: after[k] - before[k] for k in ("conditions", "student", "decode")})
        part["other"] = vec_times[-1] - sum(part.values())
        parts.append(part)
    return vec_times, parts


def _vector_figures(
    vec_times: list[float], parts: list[dict[str, float]], num_envs: int, step_s: float, with_model: bool
) -> dict:
    """The vector pass's report: its step's breakdown, the share outside the networks
    (``with_model``) and its throughput beside ``num_envs`` single steps of ``step_s`` in a row."""
    vec_s = statistics.median(vec_times)
    # Per env step, ms: the median over steps of each part of a vector step, divided by num_envs.
    result: dict = {
        "vector_step_breakdown_ms_per_env_step": {
            k: 1e3 * statistics.median(p[k] for p in parts) / num_envs for k in parts[0]
        }
    }
    if with_model:
        outside = [p["traffic"] + p["conditions"] + p["other"] for p in parts]
        result["vector_outside_model_share"] = statistics.median(outside) / vec_s
        result["non_model_env_steps_per_s"] = num_envs / statistics.median(outside)
    sequential_s = num_envs * step_s
    result.update(
        {
            "num_envs": num_envs,
            "vector_median_step_ms": 1e3 * vec_s,
            "vector_aggregate_steps_per_s": num_envs / vec_s,
            "sequential_aggregate_steps_per_s": num_envs / sequential_s,
            "batched_vs_sequential_speedup": sequential_s / vec_s,
        }
    )
    return result


def bench_backend_isolated(backend: str, run: BackendRun) -> dict:
    """:func:`bench_backend` in a fresh process: no backend shares the process with another (the
    world model's torch threads and imports, earlier rounds' envs) while it is timed."""
    cmd = [*PROBE, "--backend-probe", backend, "--scenario", run.scenario, "--steps", str(run.steps)]
    cmd += ["--num-envs", str(run.num_envs), "--seed", str(run.seed), "--warmup", str(run.warmup), "--out", "-"]
    cmd += ["--device", run.device]
    cmd += (["--checkpoint", run.checkpoint] if run.checkpoint else []) + (["--compile"] if run.compile_model else [])
    probe = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)  # its errors reach the terminal
    if probe.returncode:
        raise SystemExit(
            f"m4world bench env: the {backend} backend's run failed (exit {probe.returncode}); its error is above"
        )
    return json.loads(probe.stdout.strip().splitlines()[-1])


def _stage_seconds_reader(backend: object):  # noqa: ANN202 (a reader of seconds)
    """A reader of the world-model backend's seconds in this process per stage (crops, conditions,
    student, decode), timed from now on by a ``StageTimer`` attached to its pipeline; a checkout
    whose pipeline counts its own seconds (``--compare-tree``) is read from its counters."""
    rollouts, conditions = backend.rollouts, getattr(backend, "conditions", None)
    try:
        from world_model.rollout.timing import StageTimer
    except ImportError:

        def counters() -> dict[str, float]:
            own = dict(conditions.seconds) if conditions is not None else {}
            seconds = {**rollouts.seconds, "crops": own.get("crops", 0.0)}
            seconds["conditions"] += own.get("conditions", 0.0)
            return seconds

        return counters
    timer = rollouts.timer = conditions.timer = StageTimer()
    return lambda: dict(timer.seconds)


def median_rounds(rounds: list[dict]) -> dict:
    """Field-wise median of the rounds' numbers, nested dicts (a step's breakdown) included; ints
    (e.g. ``num_envs``) and other values are equal in every round and taken from the first."""
    out = {}
    for k, v in rounds[0].items():
        if isinstance(v, float):
            out[k] = statistics.median(r[k] for r in rounds)
        elif isinstance(v, dict):
            out[k] = median_rounds([r[k] for r in rounds])
        else:
            out[k] = v
    return out


def _digest(h, arrays) -> None:  # noqa: ANN001 (hashlib object, arrays)
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())


def _workers_venv(
    workers: int, scenario: str, num_envs: int, checkpoint: str | None, device: str
) -> gym.vector.VectorEnv:
    """A vector env of ``num_envs`` world-model sub-envs with ``config.workers`` = ``workers`` (the
    key left out at 0, so a checkout without it runs too), its models on ``device``."""
    config: dict = {**CONFIG, **({"workers": workers} if workers else {})}
    if device != "cpu":
        config["model"] = {"device": device}
    kw = {"backend": "world_model", "config": config, **({"checkpoint": checkpoint} if checkpoint else {})}
    return gym.make_vec(
        "M4World-v0", num_envs=num_envs, vectorization_mode="vector_entry_point", scenario=scenario, **kw
    )


def _vector_parts_reader(base: object):  # noqa: ANN202 (a reader of seconds)
    """A reader of the seconds so far of each part of a vector step of ``base`` (the unwrapped
    vector env): the simulation workers' parts and main's wait for them, or (no workers) the traffic,
    crops and conditions in this process; then student and decode."""
    stages = _stage_seconds_reader(base.backend)
    pool = getattr(base, "simulation_workers", None)  # None at 0 workers (or in a checkout without them)
    traffic_s = [0.0]
    if pool is None:
        for env in base.envs:
            env.advance = _timed(env.advance, traffic_s)

    def parts_so_far() -> dict[str, float]:
        s = stages()
        model = {"student": s["student"], "decode": s["decode"]}
        if pool is not None:
            return {**pool.seconds(), "workers_wait": pool.wait_s, **model}
        return {"traffic": traffic_s[0], "crops": s["crops"], "conditions": s["conditions"], **model}

    return parts_so_far


def _step_parts(before: dict[str, float], after: dict[str, float], wall: float) -> dict[str, float]:
    """One vector step's parts (the readings of :func:`_vector_parts_reader` around it), with
    ``non_model`` (everything but student and decode) and ``other`` (the non-model time no part counts)."""
    part = {k: after[k] - before[k] for k in after}
    non_model = wall - part["student"] - part["decode"]
    counted = part.get("workers_wait", sum(part.get(k, 0.0) for k in ("traffic", "crops", "conditions")))
    part["other"] = non_model - counted
    part["non_model"] = non_model
    return part


def bench_workers(
    workers: int,
    scenario: str,
    num_envs: int,
    vector_steps: int,
    warmup: int,
    seed: int,
    checkpoint: str | None,
    device: str = "cpu",
) -> dict:
    """One vector env of ``num_envs`` world-model sub-envs with ``config.workers`` = ``workers``
    (the key left out at 0, so a checkout without it runs too): ``warmup`` untimed and
    ``vector_steps`` timed steps of fixed actions (no acceleration, no steering: the same for every
    checkout and worker count). Per env step: the parts of a vector step (0 workers: traffic,
    crops, conditions in this process; K workers: their traffic, crops and conditions summed over
    the workers, i.e. work on any core, and ``workers_wait``, main's wall time waiting for them),
    student, decode and ``other`` (the rest of the non-model time); ``non_model_env_steps_per_s``:
    env steps per second of everything but student and decode; ``env_steps_per_s``: of the whole
    vector step; ``digest``: a hash of every observation, reward and flag. ``device``: the models'
    (``config.model.device``)."""
    import hashlib

    start = time.perf_counter()  # progress on stderr: a run cut short shows where it was
    venv = _workers_venv(workers, scenario, num_envs, checkpoint, device)

    def say(what: str) -> None:
        print(f"[{time.perf_counter() - start:6.1f} s] workers={workers}: {what}", file=sys.stderr, flush=True)

    say(f"{num_envs} envs made")
    t0 = time.perf_counter()
    obs, _ = venv.reset(seed=seed)
    reset_s = time.perf_counter() - t0
    say(f"reset in {reset_s:.1f} s")
    h = hashlib.sha256()
    _digest(h, obs.values())
    parts_so_far = _vector_parts_reader(venv.unwrapped)
    actions = np.zeros((num_envs, 2), np.float32)
    walls, parts = [], []
    for i in range(warmup + vector_steps):
        before = parts_so_far()
        t0 = time.perf_counter()
        obs, rewards, terminated, truncated, _ = venv.step(actions)
        wall = time.perf_counter() - t0
        after = parts_so_far()
        _digest(h, [*obs.values(), rewards, terminated, truncated])
        if i < warmup:
            continue
        walls.append(wall)
        parts.append(_step_parts(before, after, wall))
        say(f"vector step {len(walls)}: {wall:.2f} s")
    venv.close()
    per_env = {k: 1e3 * statistics.median(p[k] for p in parts) / num_envs for k in parts[0]}
    return {
        "workers": workers,
        "num_envs": num_envs,
        "vector_steps": vector_steps,
        "vector_median_step_ms": 1e3 * statistics.median(walls),
        "env_steps_per_s": num_envs / statistics.median(walls),
        "vector_reset_ms": 1e3 * reset_s,
        "breakdown_ms_per_env_step": per_env,
        "non_model_env_steps_per_s": 1e3 / per_env["non_model"],
        "digest": h.hexdigest(),
    }


def bench_workers_isolated(workers: int, args: argparse.Namespace, root: Path) -> dict:
    """:func:`bench_workers` in a fresh process whose ``m4world_env``/``world_model`` come from ``root``."""
    cmd = [
        sys.executable,
        "-c",
        RUN_FILE,
        __file__,
        "--workers-probe",
        str(workers),
        "--scenario",
        args.scenario,
        "--out",
        "-",
    ]
    cmd += ["--num-envs", str(args.num_envs), "--seed", str(args.seed), "--vector-steps", str(args.vector_steps)]
    cmd += ["--warmup", str(args.warmup if args.warmup is not None else 1)]
    cmd += ["--checkpoint", args.checkpoint] if args.checkpoint else []
    cmd += ["--device", args.device] if args.device != "cpu" else []  # a checkout may lack the option
    # root first; the rest of the path stays (packages installed with --target, e.g. on a GPU machine)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True, env=env).stdout  # stderr: progress
    return json.loads(out.strip().splitlines()[-1])


def compare_workers(args: argparse.Namespace) -> dict:
    """``--workers``: every worker count (and ``--compare-tree``'s 0) in interleaved rounds, each in
    a fresh process; the medians over rounds, the non-model throughput of each worker count over
    0 workers' (per round, then the median), and whether every run of this checkout observed the
    same."""
    here = Path(__file__).resolve().parents[2]  # the folder holding this file's m4world_env
    configs = [(f"workers={k}", k, here) for k in args.workers]
    if args.compare_tree:
        configs.append(("compare_tree workers=0", 0, Path(args.compare_tree).resolve()))
    rounds = []
    for _ in range(args.rounds):
        rounds.append({name: bench_workers_isolated(k, args, root) for name, k, root in configs})
    result: dict = {"scenario": args.scenario, "rounds": args.rounds, "device": args.device, "configs": {}}
    for name, _, _ in configs:
        runs = [rnd[name] for rnd in rounds]
        merged = median_rounds([{k: v for k, v in r.items() if k != "breakdown_ms_per_env_step"} for r in runs])
        merged["breakdown_ms_per_env_step"] = median_rounds([r["breakdown_ms_per_env_step"] for r in runs])
        merged["digest"] = sorted({r["digest"] for r in runs})
        result["configs"][name] = merged
    base = "workers=0"
    if base in result["configs"]:
        for name, k, root in configs:
            if k and root == here:
                ratios = [
                    rnd[name]["non_model_env_steps_per_s"] / rnd[base]["non_model_env_steps_per_s"] for rnd in rounds
                ]
                result[f"non_model_throughput_{name}_vs_workers=0"] = statistics.median(ratios)
        if args.compare_tree:
            ratios = [
                rnd[base]["breakdown_ms_per_env_step"]["non_model"]
                / rnd["compare_tree workers=0"]["breakdown_ms_per_env_step"]["non_model"]
                for rnd in rounds
            ]
            result["non_model_cost_workers=0_vs_compare_tree"] = statistics.median(ratios)
    ours = {d for name, _, root in configs if root == here for d in result["configs"][name]["digest"]}
    runs_of_ours = args.rounds * sum(root == here for _, _, root in configs)
    # None: a single run compares nothing (one worker count, one round)
    result["observations_identical"] = len(ours) == 1 if runs_of_ours > 1 else None
    result["per_round"] = rounds
    return result


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="m4world bench env", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument(
        "--backend",
        nargs="+",
        default=["procedural"],
        help="procedural, world_model, or world_model:QUALIFIERS: a dtype (float32, bfloat16; default auto), "
        "compile (config.model.compile) and/or "
        "no-refresh (config.model.context_refresh off) or refresh=K[,K...] (config.model.refresh_steps; "
        "default: the last two denoising steps) or refresh=all (every step), sink=N (config.model.sink_frames), "
        "denoise=N (config.model.denoising_steps), first=N (config.model.first_frame_steps), "
        "[no-]one-step-first (config.model.one_step_first_frame), keys=K[+K...] (observation_keys), "
        "threads=N|torch (config.model.threads), "
        "rollout-threads=N (config.model.rollout_threads), "
        "and checkpoint=BUNDLE (this backend's bundle instead of --checkpoint's), "
        "e.g. world_model:compile or world_model:compile:no-refresh or world_model:checkpoint=runs/x/bundle",
    )
    ap.add_argument("--scenario", default="highway_sunny_day")
    ap.add_argument("--steps", type=int, default=300, help="single-env steps per backend, split over the rounds")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (see the module docstring)")
    ap.add_argument("--num-envs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    ap.add_argument("--compile", action="store_true", help="world model: config model.compile (torch.compile)")
    ap.add_argument("--device", default="cpu", help="world model: config model.device (cpu, cuda[:N], auto)")
    ap.add_argument(
        "--warmup", type=int, default=None, help="untimed steps first (default 2; 12 for a compiled backend)"
    )
    ap.add_argument(
        "--no-isolate",
        dest="isolate",
        action="store_false",
        help="time the backends in this process (default: a fresh process per backend and round)",
    )
    ap.add_argument(
        "--workers",
        type=int,
        nargs="+",
        default=None,
        help="world model only: time a vector env of --num-envs sub-envs with each of these config.workers "
        "counts (e.g. 0 2) in interleaved rounds instead of the backends (see bench_workers)",
    )
    ap.add_argument("--vector-steps", type=int, default=5, help="--workers: timed vector steps per run")
    ap.add_argument(
        "--compare-tree",
        default=None,
        help="--workers: also time workers=0 with the packages of this checkout (e.g. another branch's worktree)",
    )
    ap.add_argument("--workers-probe", type=int, default=None, help=argparse.SUPPRESS)  # internal: one run
    ap.add_argument("--memory-probe", default=None, help=argparse.SUPPRESS)  # internal: one env's peak RSS
    ap.add_argument("--backend-probe", default=None, help=argparse.SUPPRESS)  # internal: one isolated round
    return ap


def compare_backends(args: argparse.Namespace) -> dict:
    """``--backend``: highway-env's envs and every backend in ``args.rounds`` interleaved rounds;
    the medians over rounds, each ratio to highway-env taken within its round, and each backend's
    one-env peak RSS."""
    steps = max(args.steps // args.rounds, 10)
    # Not at the top: a --compare-tree probe runs this file over a checkout that may have no bench.
    from m4world_env.bench.traffic import bench_highway_env

    def warmup_of(backend: str) -> int:
        if args.warmup is not None:
            return args.warmup
        compiled = make_kwargs(backend, None)["config"].get("model", {}).get("compile", False)
        return 12 if args.compile or compiled else 2

    rounds: list[dict] = []
    for _ in range(args.rounds):
        # highway-env and every backend measured back to back: a ratio compares numbers taken
        # within minutes of each other, so a drift of the shared machine's speed cancels out.
        hw = {e: bench_highway_env(e, max(steps // 6, 20), args.seed) for e in ("highway-v0", "highway-fast-v0")}
        rnd = {"highway_env": hw, "backends": {}}
        for backend in args.backend:
            run = BackendRun.from_args(args, steps, warmup_of(backend))
            r = bench_backend_isolated(backend, run) if args.isolate else bench_backend(backend, run)
            r["single_vs_highway_fast_v0"] = r["single_steps_per_s"] / hw["highway-fast-v0"]["steps_per_s"]
            r["vector_aggregate_vs_highway_v0"] = r["vector_aggregate_steps_per_s"] / hw["highway-v0"]["steps_per_s"]
            rnd["backends"][backend] = r
        rounds.append(rnd)
    result: dict = {"scenario": args.scenario, "rounds": args.rounds, "device": args.device, "backends": {}}
    for backend in args.backend:
        r = median_rounds([rnd["backends"][backend] for rnd in rounds])
        r["one_env_peak_rss_mb"] = peak_rss_one_env(backend, args.scenario, 50, args.seed, args.checkpoint, args.device)
        result["backends"][backend] = r
    result["highway_env"] = {
        e: median_rounds([rnd["highway_env"][e] for rnd in rounds]) for e in ("highway-v0", "highway-fast-v0")
    }
    result["per_round"] = rounds
    result["peak_rss_mb"] = own_peak_rss_mb()  # not ru_maxrss: it carries the launching process's peak
    return result


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if args.memory_probe:
        _memory_probe(args.memory_probe, args.scenario, args.steps, args.seed, args.checkpoint, args.device)
        return
    if args.workers_probe is not None:
        warmup = args.warmup if args.warmup is not None else 1
        r = bench_workers(
            args.workers_probe,
            args.scenario,
            args.num_envs,
            args.vector_steps,
            warmup,
            args.seed,
            args.checkpoint,
            args.device,
        )
        print(json.dumps(r))
        return
    if args.backend_probe:
        r = bench_backend(args.backend_probe, BackendRun.from_args(args, args.steps, args.warmup))
        print(json.dumps(r))
        return
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be >= 1, got {args.rounds}")
    result = compare_workers(args) if args.workers is not None else compare_backends(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "per_round"}, indent=2))


if __name__ == "__main__":
    main()
