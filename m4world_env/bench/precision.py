"""How much the world model's observations change between float32 and bfloat16 DiTs.

    m4world bench precision --steps 40 --out F.json [--checkpoint BUNDLE]

Runs the same episode (scenario, seed, IDM policy) twice on the world-model backend, once with
``config.model.dtype`` float32 and once bfloat16, and reports per step the mean absolute camera
difference (uint8 levels) and LiDAR difference (metres) between the two. Both runs draw the same
noise, so the difference is the precision alone, compounded over the rollout: what ``dtype="auto"``
changes for a user on a CPU without native bf16 (it runs float32 there, the checkpoint's bf16
elsewhere).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
import numpy as np

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.evaluate import make_policy

COMPARED = ("float32", "bfloat16")  # the two precisions "auto" chooses between


def episode(dtype: str, scenario: str, seed: int, steps: int, checkpoint: str | None) -> list[dict]:
    """The observations of up to ``steps`` IDM steps (plus the reset's) with the DiTs in ``dtype``."""
    kw = {"checkpoint": checkpoint} if checkpoint else {}
    env = gym.make("M4World-v0", scenario=scenario, backend="world_model", config={"model": {"dtype": dtype}}, **kw)
    obs, info = env.reset(seed=seed)
    policy = make_policy("idm", env)
    out = [obs]
    for _ in range(steps):
        obs, _r, terminated, truncated, info = env.step(policy(obs, info))
        out.append(obs)
        if terminated or truncated:
            break
    env.close()
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="m4world bench precision", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="highway_sunny_day")
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    runs = {d: episode(d, a.scenario, a.seed, a.steps, a.checkpoint) for d in COMPARED}
    rows = []
    for step, (x, y) in enumerate(zip(*runs.values(), strict=False)):
        rows.append(
            {
                "step": step,
                "camera_mean_abs_diff_levels": float(np.abs(x["cameras"].astype(np.float32) - y["cameras"]).mean()),
                "lidar_mean_abs_diff_m": float(np.abs(x["lidar"] - y["lidar"]).mean()),
            }
        )
    result = {
        "scenario": a.scenario,
        "seed": a.seed,
        "steps": len(rows) - 1,
        "max_camera_mean_abs_diff_levels": max(r["camera_mean_abs_diff_levels"] for r in rows),
        "max_lidar_mean_abs_diff_m": max(r["lidar_mean_abs_diff_m"] for r in rows),
        "per_step": rows,
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "per_step"}, indent=1))


if __name__ == "__main__":
    main()
