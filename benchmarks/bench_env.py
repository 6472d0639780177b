"""Env steps/s for 1 and N envs per backend, next to highway-env's own envs, in one run.

    PYTHONPATH=src python benchmarks/bench_env.py --out out/bench_env.json [--backend procedural]

Reports, per backend: one env's median step time and steps/s; a vector env of ``--num-envs``
(one batched backend call per step) vs the same number of single envs stepped one after another;
the split of a step into traffic (bridge) and sensor time; peak RSS. highway-v0 and highway-fast-v0
are measured in the same run. The policy is the lane-keeping reference policy; its time is not counted.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_traffic import bench_highway_env  # noqa: E402

import m4world_env  # noqa: E402, F401
from m4world_env.policies import ConstantSpeedLaneKeeping  # noqa: E402

CONFIG = {"observation_keys": ["cameras", "lidar"]}


def _time_single(env, steps: int, seed: int) -> tuple[list[float], list[float]]:
    """Per-step wall times and the bridge's share of each, for one env."""
    base = env.unwrapped
    env.reset(seed=seed)
    policy = ConstantSpeedLaneKeeping()
    totals, traffic = [], []
    for _ in range(steps):
        action = policy(base.bridge)
        t0 = time.perf_counter()
        frames = base.advance(action)
        t1 = time.perf_counter()
        (observations,) = base.backend.step([frames])
        *_, terminated, truncated, _ = base.finish_step(frames, observations)
        t2 = time.perf_counter()
        totals.append(t2 - t0)
        traffic.append(t1 - t0)
        if terminated or truncated:
            env.reset(seed=seed)
            policy = ConstantSpeedLaneKeeping()
    return totals, traffic


def bench_backend(backend: str, scenario: str, steps: int, num_envs: int, seed: int) -> dict:
    single = gym.make("M4World-v0", scenario=scenario, backend=backend, config=CONFIG)
    totals, traffic = _time_single(single, steps, seed)
    step_s = statistics.median(totals)
    result = {
        "single_median_step_ms": 1e3 * step_s,
        "single_steps_per_s": 1.0 / step_s,
        "traffic_share": statistics.median(traffic) / step_s,
        "frames_per_step": single.unwrapped.scenario.frames_per_step,
    }
    venv = gym.make_vec(
        "M4World-v0",
        num_envs=num_envs,
        vectorization_mode="vector_entry_point",
        scenario=scenario,
        backend=backend,
        config=CONFIG,
    )
    venv.reset(seed=seed)
    policies = [ConstantSpeedLaneKeeping() for _ in range(num_envs)]
    vec_times = []
    for _ in range(max(steps // num_envs, 10)):
        actions = np.stack([p(e.bridge) for p, e in zip(policies, venv.unwrapped.envs, strict=True)])
        t0 = time.perf_counter()
        venv.step(actions)
        vec_times.append(time.perf_counter() - t0)
    vec_s = statistics.median(vec_times)
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
    venv.close()
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--backend", nargs="+", default=["procedural"])
    ap.add_argument("--scenario", default="highway_sunny_day")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--num-envs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    result: dict = {"scenario": args.scenario, "backends": {}}
    for backend in args.backend:
        result["backends"][backend] = bench_backend(backend, args.scenario, args.steps, args.num_envs, args.seed)
    result["highway_env"] = {
        e: bench_highway_env(e, max(args.steps // 6, 20), args.seed) for e in ("highway-v0", "highway-fast-v0")
    }
    fast = result["highway_env"]["highway-fast-v0"]["steps_per_s"]
    slow = result["highway_env"]["highway-v0"]["steps_per_s"]
    for r in result["backends"].values():
        r["single_vs_highway_fast_v0"] = r["single_steps_per_s"] / fast
        r["vector_aggregate_vs_highway_v0"] = r["vector_aggregate_steps_per_s"] / slow
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
