"""Soak test: many env steps in a row, with resident memory sampled along the way.

    m4world bench soak --out out/soak.json
        [--procedural-steps 10000] [--world-model-steps 600] [--checkpoint BUNDLE]

Runs the procedural backend for ``--procedural-steps`` steps and the world-model backend for
``--world-model-steps`` steps (default checkpoint: an untrained tiny-preset bundle made on the fly,
which exercises the same code paths), episodes auto-restarting, under the lane-keeping policy.
Reports RSS every ``--sample-every`` steps and the growth from the first sample after warm-up
(10% of the run) to the end; exits non-zero on an error or when growth exceeds ``--max-growth``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym

from world_model.rollout.runtime import save_untrained_bundle


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * resource.getpagesize() / 2**20


def soak(backend: str, steps: int, sample_every: int, checkpoint: str | None, scenario: str) -> dict:
    import m4world_env  # noqa: F401
    from m4world_env.policies import ConstantSpeedLaneKeeping

    env = gym.make(
        "M4World-v0",
        scenario=scenario,
        backend=backend,
        checkpoint=checkpoint,
        config={"observation_keys": ["cameras", "lidar", "state"]},
    )
    base = env.unwrapped
    env.reset(seed=0)
    policy = ConstantSpeedLaneKeeping()
    samples, episodes, t0 = [], 1, time.perf_counter()
    for i in range(1, steps + 1):
        _, _, terminated, truncated, _ = env.step(policy(base.bridge))
        if terminated or truncated:
            env.reset()
            policy = ConstantSpeedLaneKeeping()
            episodes += 1
        if i % sample_every == 0 or i == steps:
            samples.append({"step": i, "rss_mb": rss_mb()})
    warm = next(s for s in samples if s["step"] >= steps // 10)
    growth = (samples[-1]["rss_mb"] - warm["rss_mb"]) / warm["rss_mb"]
    return {
        "backend": backend,
        "steps": steps,
        "episodes": episodes,
        "seconds": time.perf_counter() - t0,
        "rss_after_warmup_mb": warm["rss_mb"],
        "rss_end_mb": samples[-1]["rss_mb"],
        "growth_after_warmup": growth,
        "samples": samples,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="m4world bench soak", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--procedural-steps", type=int, default=10_000)
    ap.add_argument("--world-model-steps", type=int, default=600)
    ap.add_argument("--checkpoint", default=None, help="bundle for the world-model run (default: tiny, untrained)")
    ap.add_argument("--scenario", default="highway_sunny_day")
    ap.add_argument("--sample-every", type=int, default=100)
    ap.add_argument("--max-growth", type=float, default=0.05)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = args.checkpoint or str(save_untrained_bundle(Path(tmp) / "tiny_bundle"))
        runs = []
        if args.procedural_steps:
            runs.append(soak("procedural", args.procedural_steps, args.sample_every, None, args.scenario))
        if args.world_model_steps:
            runs.append(soak("world_model", args.world_model_steps, args.sample_every, checkpoint, args.scenario))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(runs, indent=1))
    ok = True
    for r in runs:
        print(
            f"{r['backend']:12s} {r['steps']:6d} steps, {r['episodes']} episodes, {r['seconds']:.0f} s, "
            f"RSS {r['rss_after_warmup_mb']:.0f} -> {r['rss_end_mb']:.0f} MB ({100 * r['growth_after_warmup']:+.1f}%)"
        )
        ok &= r["growth_after_warmup"] <= args.max_growth
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
