"""The env's camera views or LiDAR beside the ground truth's: one episode driven on both backends, one image.

    m4world bench side_by_side --scenario highway_sunny_day --seed 3 --steps 0 5 15 30 36 \
        --out docs/images/world_model_vs_truth.jpg [--checkpoint BUNDLE] [--policy lane_keeping]
    m4world bench side_by_side --sensor lidar --seed 1 --steps 20 --out docs/images/lidar_vs_truth.png

The same scenario, seed and policy on ``backend="procedural"`` (the ground truth) and
``backend="world_model"``; for each step asked, a row of the ground truth's six views above a row of
the world model's (FRONT_LEFT ... BACK_LEFT), or with ``--sensor lidar`` their LiDAR range maps over
the :data:`LIDAR_AHEAD_DEG` degrees ahead (the render mosaic's colours: near warm, far cold, no
return black). An episode that ends first shows its last step.
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
from world_model.sim.mosaic import lidar_image

GAP_PX = 4  # white space between the step pairs
LIDAR_AHEAD_DEG = 120.0  # the LiDAR's azimuths shown, centred straight ahead: the road a policy reads
LIDAR_COLUMN_PX = 3  # pixels per azimuth column: a car 25 m ahead, 11 columns, stays visible


def lidar_ahead(ranges: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: a range map's (beams, azimuth) columns within ``LIDAR_AHEAD_DEG`` / 2 of
    straight ahead (the middle column), colour-mapped as the render mosaic draws it."""
    half = round(ranges.shape[1] * LIDAR_AHEAD_DEG / 720.0)
    ahead = ranges[:, ranges.shape[1] // 2 - half : ranges.shape[1] // 2 + half]
    return lidar_image(ahead, ahead.shape[1] * LIDAR_COLUMN_PX)


def views_at(
    backend: str,
    scenario: str,
    seed: int,
    policy: str,
    steps: list[int],
    checkpoint: str | None,
    sensor: str = "cameras",
) -> list:
    """(V, H, W, 3) uint8 views at each of ``steps`` (the last step reached where the episode ended
    first): the cameras, or with ``sensor="lidar"`` one view, :func:`lidar_ahead`."""
    kwargs = {"checkpoint": checkpoint} if backend == "world_model" and checkpoint else {}
    env = gym.make("M4World-v0", scenario=scenario, backend=backend, **kwargs)
    act = make_policy(policy, env)
    obs, info = env.reset(seed=seed)

    def seen(observation: dict) -> np.ndarray:
        return observation["cameras"] if sensor == "cameras" else lidar_ahead(observation["lidar"])[None]

    out, step = {0: seen(obs)}, 0
    while step < max(steps):
        obs, _r, terminated, truncated, info = env.step(act(obs, info))
        step += 1
        out[step] = seen(obs)
        if terminated or truncated:
            break
    env.close()
    return [out[min(s, step)] for s in steps]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench side_by_side", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="highway_sunny_day")
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--policy", default="lane_keeping")
    p.add_argument("--steps", type=int, nargs="+", default=[0, 5, 15, 30, 36])
    p.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    p.add_argument("--sensor", choices=("cameras", "lidar"), default="cameras", help="what each row shows")
    p.add_argument("--scale", type=int, default=2, help="integer upscaling of the image")
    p.add_argument("--out", required=True, help="image file (.jpg or .png)")
    a = p.parse_args(argv)
    if min(a.steps) < 0:
        p.error("--steps must be 0 or more")
    truth = views_at("procedural", a.scenario, a.seed, a.policy, a.steps, None, a.sensor)
    model = views_at("world_model", a.scenario, a.seed, a.policy, a.steps, a.checkpoint, a.sensor)
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
