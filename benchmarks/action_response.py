"""Do the ego's actions show in the observations? The same episode driven two ways.

    PYTHONPATH=src python benchmarks/action_response.py --out F.json \
        [--backend procedural world_model world_model:sink=0] [--actions 0,0 -1,0] [--steps 40]

For each backend, one episode (scenario, seed; on the world model the same noise) is run twice:
once holding the first ``--actions`` vector at every step, once the second (default: hold the
speed vs brake fully). Reported per step: how far the two runs' observations are apart, cameras as
the mean absolute difference (uint8 levels), LiDAR as the mean absolute range difference
(metres). On the procedural backend that is the ground truth's response to the action; a world
model that ignored the action would show none, one that responds like the scene does shows a
similar curve. ``response_*`` is each backend's median over steps divided by the procedural
backend's (1: as much as the ground truth). Backend specs are ``bench_env.py``'s (qualifiers such as
``world_model:sink=0`` or ``world_model:no-refresh``), so model options are compared in one run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_env import _make_kwargs  # noqa: E402

import m4world_env  # noqa: E402,F401  (registers M4World-v0)


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


def apart(a: list[dict], b: list[dict]) -> dict[str, list[float]]:
    """Per step (over the steps both runs reached): the two runs' camera and LiDAR differences."""
    n = min(len(a), len(b))
    cams = [float(np.abs(a[i]["cameras"].astype(np.float32) - b[i]["cameras"]).mean()) for i in range(n)]
    lidar = [float(np.abs(a[i]["lidar"] - b[i]["lidar"]).mean()) for i in range(n)]
    return {"cameras": cams, "lidar": lidar}


def parse_action(text: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in text.split(",")], np.float32)
    except ValueError:
        raise SystemExit(f"--actions takes comma-separated numbers such as 0,0 or -1,0, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
    result: dict = {"scenario": a.scenario, "seed": a.seed, "actions": a.actions, "backends": {}}
    for backend in a.backend:
        kw = _make_kwargs(backend, a.checkpoint if backend.startswith("world_model") else None)
        kw["config"] = {**kw["config"], "action_type": "continuous"}
        curves = apart(*(episode(kw, a.scenario, a.seed, h, a.steps) for h in held))
        result["backends"][backend] = {
            "steps": len(curves["cameras"]) - 1,
            **{f"median_{k}": statistics.median(v[1:]) for k, v in curves.items()},
            "per_step": curves,
        }
        print(backend, {k: round(v, 3) for k, v in result["backends"][backend].items() if k.startswith("median")})
    truth = result["backends"]["procedural"]
    for r in result["backends"].values():
        for k in ("cameras", "lidar"):
            r[f"response_{k}"] = r[f"median_{k}"] / truth[f"median_{k}"] if truth[f"median_{k}"] else None
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
