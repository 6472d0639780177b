"""Do the ego's actions show in the observations? The same episode driven two ways.

    m4world bench action_response --out F.json \
        [--backend procedural world_model world_model:sink=0] [--actions 0,0 -1,0] [--steps 40]

For each backend, one episode (scenario, seed; on the world model the same noise) is run twice:
once holding the first ``--actions`` vector at every step, once the second (default: hold the
speed vs brake fully). Reported per step: how far the two runs' observations are apart, cameras as
the mean absolute difference (uint8 levels), LiDAR as the mean absolute range difference
(metres). On the procedural backend that is the ground truth's response to the action; a world
model that ignored the action would show none, one that responds like the scene does shows a
similar curve. ``response_*`` is each backend's median over steps divided by the procedural
backend's (1: as much as the ground truth).

The LiDAR's mean hides where a response comes from: the ground truth's ranges change only on the
few cells whose object moved, a world model's may wander a little everywhere. So the LiDAR is
also split by the ground truth's own difference at each step: ``lidar_moved``, the mean range
difference on the cells where the ground truth's two runs differ by more than ``MOVED_M``
(``response_lidar_moved``: its median against the ground truth's there), and ``lidar_still``, the
mean on every other cell (metres the backend changed where the scene did not).

Backend specs are ``m4world bench env``'s (qualifiers such as ``world_model:sink=0`` or
``world_model:no-refresh``), so model options are compared in one run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.bench.env import make_kwargs

MOVED_M = 0.5  # a LiDAR cell whose range differs by more than this between the truth's runs moved
RESPONSES = ("cameras", "lidar", "lidar_moved")  # the curves scored against the ground truth's


def episode(kwargs: dict, scenario: str, seed: int, action: np.ndarray, steps: int) -> list[dict]:
    """The observations of the reset and of up to ``steps`` steps holding ``action``."""
    env = gym.make("M4World-v0", scenario=scenario, **kwargs)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        obs, _r, terminated, truncated, _ = env.step(action)
        out.append(obs)
        if terminated or truncated:
            break
    env.close()
    return out


def apart(a: list[dict], b: list[dict], moved: list[np.ndarray]) -> dict[str, list[float]]:
    """Per step (over the steps both runs and ``moved`` reach): the two runs' camera and LiDAR
    differences, and the LiDAR's on the cells where the ground truth moved (``moved``, per step)
    and on the others (``lidar_moved``, ``lidar_still``)."""
    n = min(len(a), len(b), len(moved))
    cams = [float(np.abs(a[i]["cameras"].astype(np.float32) - b[i]["cameras"]).mean()) for i in range(n)]
    lidar = [np.abs(a[i]["lidar"] - b[i]["lidar"]) for i in range(n)]
    inside, outside = zip(*map(split_mean, lidar, moved), strict=False)
    return {
        "cameras": cams,
        "lidar": [float(d.mean()) for d in lidar],
        "lidar_moved": list(inside),
        "lidar_still": list(outside),
    }


def split_mean(values: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Mean of ``values`` where ``mask`` holds and where it does not (0 for an empty part)."""
    inside, outside = values[mask], values[~mask]
    return (float(inside.mean()) if inside.size else 0.0, float(outside.mean()) if outside.size else 0.0)


def summarize(curves: dict[str, list[float]]) -> dict:
    """One backend's curves (:func:`apart`) with their medians over the steps (the reset, step 0,
    left out: both runs start alike)."""
    return {
        "steps": len(curves["cameras"]) - 1,
        **{f"median_{k}": statistics.median(v[1:]) for k, v in curves.items()},
        "per_step": curves,
    }


def add_responses(backends: dict[str, dict], truth: str) -> None:
    """Each backend's ``response_*``: its median over the ``truth`` backend's (None where the truth
    did not move at all)."""
    reference = backends[truth]
    for r in backends.values():
        for k in RESPONSES:
            r[f"response_{k}"] = r[f"median_{k}"] / reference[f"median_{k}"] if reference[f"median_{k}"] else None


def parse_action(text: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in text.split(",")], np.float32)
    except ValueError:
        raise SystemExit(f"--actions takes comma-separated numbers such as 0,0 or -1,0, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench action_response", description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", nargs="+", default=["procedural", "world_model", "world_model:sink=0"])
    p.add_argument("--actions", nargs=2, default=["0,0", "-1,0"], metavar="A", help="the two continuous actions held")
    p.add_argument("--scenario", default="highway_sunny_day")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    if "procedural" not in a.backend:
        p.error("--backend needs procedural: the ground truth every response is divided by")
    held = [parse_action(s) for s in a.actions]
    result: dict = {"scenario": a.scenario, "seed": a.seed, "actions": a.actions, "moved_m": MOVED_M, "backends": {}}
    moved = None
    for backend in ["procedural", *(b for b in a.backend if b != "procedural")]:
        kw = make_kwargs(backend, a.checkpoint if backend.startswith("world_model") else None)
        kw["config"] = {**kw["config"], "action_type": "continuous"}
        runs = [episode(kw, a.scenario, a.seed, h, a.steps) for h in held]
        if moved is None:  # the ground truth runs first: where its ranges changed
            moved = [np.abs(x["lidar"] - y["lidar"]) > MOVED_M for x, y in zip(*runs, strict=False)]
        result["backends"][backend] = summarize(apart(*runs, moved=moved))
        print(backend, {k: round(v, 3) for k, v in result["backends"][backend].items() if k.startswith("median")})
    add_responses(result["backends"], truth="procedural")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(
        json.dumps(
            {b: {k: v for k, v in r.items() if k != "per_step"} for b, r in result["backends"].items()}, indent=1
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
