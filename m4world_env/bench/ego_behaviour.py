"""How varied the recorded ego's driving is, per driving style: braking, accelerating, lane changes.

    m4world bench ego_behaviour --episodes 4 --duration 30 --out ego_behaviour.json

Drives the recorder's episodes (``m4world_env.recorder.drive_episode``: the same randomized
scenarios, seeds and autopilot styles as ``m4world record``, no sensors rendered) and reports,
per style and action type, averaged over the episodes: the time fraction spent braking
(acceleration < ``--brake``) and accelerating (> ``--accelerate``), the speed range (5th to 95th
percentile), lane changes per minute and the mean absolute yaw rate. A style that teaches the
world model what an action does has to make these differ from "steady".
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from m4world_env.config import ACTION_TYPES
from m4world_env.policies import DRIVING_STYLES
from m4world_env.recorder import RecordConfig, drive_episode, episode_seed, scenario_key
from m4world_env.scenario import load_scenario
from world_model.scene import SceneFrame


def episode_stats(frames: list[SceneFrame], brake: float, accelerate: float) -> dict[str, float]:
    """Kinematic statistics of one episode's ego (see the module docstring)."""
    acc = np.array([f.ego.acceleration for f in frames])
    speed = np.array([f.ego.speed for f in frames])
    lanes = [f.ego.lane_id.rsplit(">", 1)[-1] for f in frames]
    minutes = max(frames[-1].time - frames[0].time, 1e-9) / 60.0
    return {
        "braking_fraction": float(np.mean(acc < brake)),
        "accelerating_fraction": float(np.mean(acc > accelerate)),
        "speed_range_mps": float(np.percentile(speed, 95) - np.percentile(speed, 5)),
        "lane_changes_per_min": sum(a != b for a, b in zip(lanes, lanes[1:], strict=False)) / minutes,
        "mean_abs_yaw_rate_deg_s": float(np.degrees(np.mean(np.abs([f.ego.yaw_rate for f in frames])))),
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(
        prog="m4world bench ego_behaviour", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scenario", nargs="+", default=["highway_sunny_day", "highway_dense_rain_dusk"])
    p.add_argument("--styles", nargs="+", default=list(DRIVING_STYLES))
    p.add_argument("--action-type", nargs="+", default=list(ACTION_TYPES), choices=ACTION_TYPES)
    p.add_argument("--episodes", type=int, default=4, help="episodes per scenario and style")
    p.add_argument("--duration", type=float, default=30.0, help="seconds per episode")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--brake", type=float, default=-1.5, help="m/s^2 below which the ego counts as braking")
    p.add_argument("--accelerate", type=float, default=1.0, help="m/s^2 above which it counts as accelerating")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)

    results: dict[str, dict] = {}
    for action_type in args.action_type:
        for style in args.styles:
            cfg = RecordConfig(
                scenarios=args.scenario, duration=args.duration, action_type=action_type, styles=(style,)
            )
            stats = [
                episode_stats(
                    drive_episode(load_scenario(name), episode_seed(args.seed, scenario_key(name), e), cfg),
                    args.brake,
                    args.accelerate,
                )
                for name in args.scenario
                for e in range(args.episodes)
            ]
            row = {k: float(np.mean([s[k] for s in stats])) for k in stats[0]}
            results[f"{action_type}/{style}"] = row
            print(f"{action_type:>13} {style:>13}: " + ", ".join(f"{k}={v:.3f}" for k, v in row.items()))
    if args.out:
        args.out.write_text(json.dumps({"args": vars(args) | {"out": str(args.out)}, "results": results}, indent=1))
    return results


if __name__ == "__main__":
    main()
