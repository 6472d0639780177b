"""The env's camera views beside the ground truth's: one episode driven on both backends, one image.

    m4world bench side_by_side --scenario highway_sunny_day --seed 3 --steps 0 5 15 30 36 \
        --out docs/images/world_model_vs_truth.jpg [--checkpoint BUNDLE] [--policy lane_keeping]

The same scenario, seed and policy on ``backend="procedural"`` (the ground truth) and
``backend="world_model"``; for each step asked, a row of the ground truth's six views above a row of
the world model's (FRONT_LEFT ... BACK_LEFT). An episode that ends first shows its last step.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
from PIL import Image

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.evaluate import make_policy

GAP_PX = 4  # white space between the step pairs


def views_at(backend: str, scenario: str, seed: int, policy: str, steps: list[int], checkpoint: str | None) -> list:
    """(V, H, W, 3) uint8 views at each of ``steps`` (the last step reached where the episode ended first)."""
    kwargs = {"checkpoint": checkpoint} if backend == "world_model" and checkpoint else {}
    env = gym.make("M4World-v0", scenario=scenario, backend=backend, **kwargs)
    act = make_policy(policy, env)
    obs, info = env.reset(seed=seed)
    out, step = {0: obs["cameras"]}, 0
    while step < max(steps):
        obs, _r, terminated, truncated, info = env.step(act(obs, info))
        step += 1
        out[step] = obs["cameras"]
        if terminated or truncated:
            break
    env.close()
    return [out[min(s, step)] for s in steps]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench side_by_side", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="highway_sunny_day")
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--policy", default="lane_keeping")
    p.add_argument("--steps", type=int, nargs="+", default=[0, 5, 15, 30, 36])
    p.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    p.add_argument("--scale", type=int, default=2, help="integer upscaling of the image")
    p.add_argument("--out", required=True, help="image file (.jpg or .png)")
    a = p.parse_args(argv)
    if min(a.steps) < 0:
        p.error("--steps must be 0 or more")
    truth = views_at("procedural", a.scenario, a.seed, a.policy, a.steps, None)
    model = views_at("world_model", a.scenario, a.seed, a.policy, a.steps, a.checkpoint)
    rows = []
    for t, m in zip(truth, model, strict=True):
        pair = [np.concatenate(list(views), axis=1) for views in (t, m)]
        width = max(r.shape[1] for r in pair)  # a bundle of other sensors than the env's rig: padded white
        pair = np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in pair])
        rows += [pair, np.full((GAP_PX, width, 3), 255, np.uint8)]
    image = np.concatenate(rows[:-1], axis=0)
    image = image.repeat(a.scale, axis=0).repeat(a.scale, axis=1)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(a.out, quality=90)
    print(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
