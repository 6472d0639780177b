"""What each zoo member decides from the world model's sensors and from the ground truth's, along
the same states: where a policy's score on the world model parts from its score on the ground
truth before any closed loop can amplify it.

    m4world bench policy_reads --out F.json [--scenarios highway_sunny_day ...] [--seeds 0 1 2 3] \
        [--steps 20] [--checkpoint BUNDLE]

For each scenario and seed, one episode: the built-in ``lane_keeping`` policy drives
``backend="procedural"`` (the ground truth) and its very actions are fed to ``backend="world_model"``
(cameras and LiDAR), both reset with the seed, so the traffic is the same on both. Every zoo member
rides along twice, built with the same seed: one copy reads the ground truth's observations, the
other the world model's, each with the ego's speed (the same on both); neither drives. A member's
memory (the gap's rate of change, the lane's last reading, a command delay) follows its own copy's
readings, as it would in a closed loop.

Per scenario and member (seeds and steps pooled): the mean over steps of the two copies'
difference in acceleration and in steering, in action units ([-1, 1]), absolute (``accel``,
``steer``) and signed (``steer_bias``: world model minus ground truth; a member that steers to one
side on the world model's views). A markdown table of each scenario's members, the largest
differences first, is printed; the JSON holds the figures and the settings.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np

from m4world_env import zoo
from m4world_env.bench.lane_markings import DEFAULT_SCENARIOS  # the agreement report's scenarios
from m4world_env.same_states import (
    model_env_kwargs,
    pooled_by_scenario,
    replay_main,
    replay_settings,
    replayed_steps,
)

ROWS_SHOWN = 6  # of each scenario's members in the printed table, the largest differences first


def episode(scenario: str, seed: int, steps: int, model: dict, members: Sequence[str]) -> list[np.ndarray]:
    """Up to ``steps`` policy steps of ``scenario``: per step, (members, 2) the world model's copy's
    action minus the ground truth's copy's (acceleration, steering)."""
    out = []
    copies: list[tuple[zoo.SensorPolicy, zoo.SensorPolicy]] = []
    for step in replayed_steps(scenario, seed, steps, model):
        if not copies:  # the members read the env's own geometry
            geometry = zoo.SensorGeometry.of_env(step.truth)
            copies = [(m.build(geometry, seed), m.build(geometry, seed)) for m in map(zoo.member, members)]
        info = {"speed": step.truth_info["speed"]}
        apart = [on_model(step.model_obs, info) - on_truth(step.truth_obs, info) for on_truth, on_model in copies]
        out.append(np.stack(apart))
    return out


def figures(differences: list[np.ndarray], members: Sequence[str]) -> dict[str, dict[str, float]]:
    """Per member: mean absolute acceleration and steering differences, and the mean signed steering one."""
    if not differences:
        return {}
    d = np.stack(differences)  # (steps, members, 2)
    return {
        m: {
            "accel": float(np.abs(d[:, i, 0]).mean()),
            "steer": float(np.abs(d[:, i, 1]).mean()),
            "steer_bias": float(d[:, i, 1].mean()),
        }
        for i, m in enumerate(members)
    }


def table(results: dict[str, dict]) -> str:
    """A markdown table: per scenario its :data:`ROWS_SHOWN` members of largest differences."""
    head = ["scenario", "member", "accel", "steer", "steer bias"]
    rows = []
    for scenario, per in results.items():
        ranked = sorted(per.items(), key=lambda kv: -(kv[1]["accel"] + kv[1]["steer"]))
        rows += [
            [scenario, m, f"{f['accel']:.3f}", f"{f['steer']:.3f}", f"{f['steer_bias']:+.3f}"]
            for m, f in ranked[:ROWS_SHOWN]
        ]
    return "\n".join("| " + " | ".join(row) + " |" for row in [head, ["---"] * len(head), *rows])


def run(scenarios: list[str], seeds: list[int], steps: int, checkpoint: str | None) -> dict:
    """Every episode; the figures per scenario (seeds pooled), with the settings."""
    members = list(zoo.members())
    model = model_env_kwargs(("cameras", "lidar"), checkpoint)
    pooled = pooled_by_scenario(scenarios, seeds, lambda s, seed: episode(s, seed, steps, model, members))
    results = {scenario: figures(differences, members) for scenario, differences in pooled.items()}
    return {**replay_settings(scenarios, seeds, steps, checkpoint), "members": members, "results": results}


def main(argv: list[str] | None = None) -> int:
    return replay_main("m4world bench policy_reads", __doc__, (DEFAULT_SCENARIOS, (0, 1, 2, 3), 20), run, table, argv)


if __name__ == "__main__":
    sys.exit(main())
