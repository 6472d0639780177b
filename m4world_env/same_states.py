"""The ground truth's episode replayed on another backend: what the same-states benchmarks share.

``lane_keeping`` drives ``backend="procedural"`` (the ground truth) and its very actions are fed to
a second env (``gym.make`` keywords), both reset with the seed, so the traffic is the same on both;
an episode stops when either env ends. :func:`replayed_steps` yields each step's envs and
observations (the ground truth's ``scene_frame`` is the scene both show);
:func:`model_env_kwargs` the world-model env observing some sensors, :func:`pooled_by_scenario` an
episode's readings pooled over the seeds, :func:`replay_settings` the settings every result
records, :func:`replay_main` their shared command.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.evaluate import make_policy
from m4world_env.scenario import ScenarioError, load_scenario
from world_model.cli_args import check_out, positive_int, seed

POLICY = "lane_keeping"


class ReplayStep(NamedTuple):
    """One policy step on both envs (their unwrapped envs: ``truth.scene_frame``, ``model.lidar_spec``)."""

    truth: Any
    truth_obs: dict
    model: Any
    model_obs: dict
    truth_info: dict  # the ground truth's step info (the ego's speed: the same on both)


def replayed_steps(scenario: str, seed: int, steps: int, model: dict) -> Iterator[ReplayStep]:
    """Up to ``steps`` policy steps of ``scenario``, each once both envs took it: the ``model`` env
    (gym.make keywords) fed the ground truth's very actions."""
    truth_env = gym.make("M4World-v0", scenario=scenario, backend="procedural")
    model_env = gym.make("M4World-v0", scenario=scenario, **model)
    try:
        act = make_policy(POLICY, truth_env)
        obs, info = truth_env.reset(seed=seed)
        model_env.reset(seed=seed)
        for _ in range(steps):
            action = act(obs, info)
            obs, _r, t_term, t_trunc, info = truth_env.step(action)
            model_obs, _r, m_term, m_trunc, _ = model_env.step(action)
            yield ReplayStep(truth_env.unwrapped, obs, model_env.unwrapped, model_obs, info)
            if t_term or t_trunc or m_term or m_trunc:
                break
    finally:
        truth_env.close()
        model_env.close()


def model_env_kwargs(sensors: Sequence[str], checkpoint: str | None) -> dict:
    """gym.make keywords of the world-model env that observes ``sensors`` ("cameras", "lidar")
    only, the bundle ``checkpoint`` where given."""
    kw: dict = {"backend": "world_model", "config": {"observation_keys": list(sensors)}}
    return {**kw, "checkpoint": checkpoint} if checkpoint else kw


def pooled_by_scenario(
    scenarios: Sequence[str], seeds: Sequence[int], episode: Callable[[str, int], list[Any]]
) -> dict[str, list[Any]]:
    """Per scenario, the readings of its episodes over ``seeds`` in one list (``episode(scenario,
    seed)``: one episode's, a reading a frame); each episode's count reported on stderr as it ends."""
    pooled: dict[str, list[Any]] = {}
    for scenario in scenarios:
        pooled[scenario] = []
        for s in seeds:
            found = episode(scenario, s)
            pooled[scenario] += found
            print(f"{scenario} seed {s}: {len(found)} frames read", file=sys.stderr, flush=True)
    return pooled


def replay_settings(scenarios: list[str], seeds: list[int], steps: int, checkpoint: str | None) -> dict:
    """The settings every same-states benchmark's result records beside its own."""
    return {"scenarios": scenarios, "seeds": seeds, "steps": steps, "checkpoint": checkpoint, "policy": POLICY}


def replay_main(
    prog: str,
    doc: str,
    defaults: tuple[Sequence[str], Sequence[int], int],
    run: Callable[[list[str], list[int], int, str | None], dict],
    table: Callable[[dict], str],
    argv: list[str] | None,
) -> int:
    """A same-states benchmark's command, described by the first paragraph of its module's ``doc``:
    --scenarios, --seeds, --steps (``defaults``), --checkpoint and --out (a JSON file; unwritable, or
    an unknown scenario, refused by name); ``run``'s result written there as JSON and its
    ``results`` printed by ``table``."""
    scenarios, seeds, steps = defaults
    p = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", default=list(scenarios))
    p.add_argument("--seeds", type=seed, nargs="+", default=list(seeds))
    p.add_argument("--steps", type=positive_int, default=steps, help="policy steps per episode (at most)")
    p.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    p.add_argument("--out", required=True, help="JSON file")
    a = p.parse_args(argv)
    try:
        check_out(a.out, "file")
        for scenario in a.scenarios:
            load_scenario(scenario)
    except (ValueError, ScenarioError) as e:
        p.error(str(e))
    result = run(a.scenarios, a.seeds, a.steps, a.checkpoint)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(table(result["results"]))
    return 0
