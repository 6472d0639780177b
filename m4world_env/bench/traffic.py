"""Median TrafficBridge step time next to highway-env's own env.step, measured in one run.

    m4world bench traffic --out bench_traffic.json

A bridge step is one policy step (``frames_per_step`` sensor frames, each with its SceneFrame).
highway-env's steps include its Kinematics observation and reward, no rendering.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-v0 / highway-fast-v0)
import numpy as np

from m4world_env.policies import IDMAutopilot
from m4world_env.scenario import load_scenario
from m4world_env.traffic import TrafficBridge

SCENARIOS = ("highway_sunny_day", "highway_dense_rain_dusk", "roundabout_fog", "merge_cut_in")


def bench_bridge(name: str, steps: int, seed: int) -> dict:
    s = load_scenario(name)
    b = TrafficBridge(s, "continuous")
    b.reset(seed=seed)
    pilot = IDMAutopilot(seed=seed)
    times, vehicles = [], []
    for _ in range(steps):
        action = pilot(b)  # the policy is not timed
        t0 = time.perf_counter()
        b.step(action)
        times.append(time.perf_counter() - t0)
        vehicles.append(len(b.road.vehicles) + len(b.road.objects))
        if b.truncated or b.crashed:
            b.reset(seed=seed)
    med = statistics.median(times)
    return {
        "median_step_ms": 1e3 * med,
        "steps_per_s": 1.0 / med,
        "frames_per_step": s.frames_per_step,
        "median_ms_per_frame": 1e3 * med / s.frames_per_step,
        "median_objects": statistics.median(vehicles),
    }


def bench_highway_env(env_id: str, steps: int, seed: int) -> dict:
    env = gym.make(env_id)
    env.reset(seed=seed)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(1)  # IDLE
        times.append(time.perf_counter() - t0)
        if terminated or truncated:
            env.reset(seed=seed)
    cfg = env.unwrapped.config
    med = statistics.median(times)
    return {
        "median_step_ms": 1e3 * med,
        "steps_per_s": 1.0 / med,
        "simulation_steps_per_step": int(cfg["simulation_frequency"] // cfg["policy_frequency"]),
        "vehicles_count": cfg["vehicles_count"],
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        prog="m4world bench traffic", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    np.random.seed(args.seed)  # highway-env's own envs still draw from the global RNG in places
    result = {
        "machine": {
            "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(),
        },
        "bridge": {n: bench_bridge(n, args.steps, args.seed) for n in SCENARIOS},
        "highway_env": {e: bench_highway_env(e, args.steps // 3, args.seed) for e in ("highway-v0", "highway-fast-v0")},
    }
    args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
