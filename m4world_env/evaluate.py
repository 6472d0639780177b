"""Scoring harness: run a driving policy over scenarios and report NAVSIM-style metrics.

``m4world eval --policy idm --scenarios highway_sunny_day merge_cut_in --episodes 5`` prints a table
per scenario and overall (collision rate, off-road rate, progress, TTC violations, comfort, PDMS) and
writes JSON. Every episode's seed is recorded: ``m4world demo --scenario S --seed SEED --policy P``
replays it with a video.

A policy is ``callable(observation: dict, info: dict) -> action``. ``--policy`` takes a built-in name
(:data:`BUILTIN_POLICIES`, which read the traffic state), a zoo member's name (policies that see,
:mod:`m4world_env.zoo`; ``name`` or ``name@vN``) or ``module:attr``; when ``attr`` is a class or a
factory taking the env (``attr(env)``), it is called once per env to build the policy.
"""

from __future__ import annotations

import importlib
import inspect
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m4world_env.scenario import load_scenario

if TYPE_CHECKING:
    import gymnasium as gym

    from m4world_env.config import EnvConfig

Policy = Callable[[dict, dict], Any]
AGGREGATED = ("collision", "off_road", "progress", "ttc_violation", "comfort", "pdms", "return", "distance_m")
# Reported by scenarios scored along a route (log replay); averaged over the episodes that have them.
ROUTE_AGGREGATED = ("off_route", "route_deviation_max_m")


def episode_policy_seed(env: gym.Env) -> int:
    """A named policy's seed for the episode ``env`` has just been reset into: drawn from the env's
    generator, so an episode replays from the env's seed alone."""
    return int(env.unwrapped.np_random.integers(2**31 - 1))


def _builtin_policy(name: str, env: gym.Env) -> Policy:
    from m4world_env import policies, zoo

    base = env.unwrapped
    seed = episode_policy_seed(env)
    if is_zoo_policy(name):
        return zoo.member(name).build(zoo.SensorGeometry.of_env(env), seed)
    if name == "random":
        rand = policies.RandomPolicy(seed=seed)
        return lambda obs, info: rand(base.bridge)
    if name == "idm":
        auto = policies.IDMAutopilot(seed=seed)
        return lambda obs, info: auto(base.bridge)
    if name == "lane_keeping":
        keep = policies.ConstantSpeedLaneKeeping()
        return lambda obs, info: keep(base.bridge)
    raise ValueError(f"unknown built-in policy {name!r}; choose one of {BUILTIN_POLICIES} or give module:callable")


BUILTIN_POLICIES = ("random", "lane_keeping", "idm")


def is_zoo_policy(spec: object) -> bool:
    """Whether ``spec`` names a zoo member (``name`` or ``name@vN``)."""
    from m4world_env import zoo

    return isinstance(spec, str) and spec.partition("@v")[0] in zoo.members()


def is_named_policy(spec: object) -> bool:
    """A built-in or zoo name: such a policy is built afresh for every episode."""
    return spec in BUILTIN_POLICIES or is_zoo_policy(spec)


def make_policy(spec: str, env: gym.Env) -> Policy:
    """Build a policy for ``env`` from a built-in name, a zoo member's name or a ``module:attr`` spec."""
    if is_named_policy(spec):
        return _builtin_policy(spec, env)
    if ":" not in spec:
        raise ValueError(
            f"policy {spec!r} is neither a built-in {BUILTIN_POLICIES}, a zoo member (m4world zoo lists them) "
            "nor 'module:callable'"
        )
    module_name, attr = spec.split(":", 1)
    try:
        obj = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"cannot load policy {spec!r}: {e}") from e
    if not callable(obj):
        raise ValueError(f"policy {spec!r} is a {type(obj).__name__}, not a callable or a class")
    if inspect.isclass(obj):
        return obj(env)
    # A policy takes (obs, info); a factory takes the env alone, whatever its parameter is called.
    positional = [
        p
        for p in inspect.signature(obj).parameters.values()
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty
    ]
    return obj(env) if len(positional) == 1 else obj


def run_episode(env: gym.Env, policy: Policy | str, seed: int, max_steps: int | None = None) -> dict[str, float]:
    """One episode; returns the env's final ``episode_metrics`` plus the seed.

    A built-in or zoo policy name is instantiated after the reset (its state is per episode and its seed
    comes from the env's seeded RNG, so an episode replays from its seed alone).
    """
    obs, info = env.reset(seed=seed)
    if isinstance(policy, str):
        policy = make_policy(policy, env)
    steps = 0
    while True:
        obs, _reward, terminated, truncated, info = env.step(policy(obs, info))
        steps += 1
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            break
    return {**info["episode_metrics"], "seed": seed}


def aggregate(episodes: Sequence[dict[str, float]]) -> dict[str, float]:
    """Means of the reported metrics over episodes (rates for the indicator metrics)."""
    if not episodes:
        return {}
    out = {k: float(np.mean([e[k] for e in episodes])) for k in AGGREGATED}
    for k in ROUTE_AGGREGATED:
        values = [e[k] for e in episodes if k in e]
        if values:
            out[k] = float(np.mean(values))
    out["episodes"] = float(len(episodes))
    return out


@dataclass(frozen=True)
class EvalRequest:
    """What an evaluation runs, on one machine (:func:`evaluate`) or on Ray workers
    (:func:`m4world_env.cluster.evaluate_on_ray`): ``policy`` for ``episodes`` episodes on each of
    ``scenarios`` (names or YAML paths), episode ``e`` seeded ``seed + e``, in envs of ``backend``
    with ``checkpoint`` and the env ``config``, each episode at most ``max_steps`` steps (None: to
    its end). Checked when made, before any env is built.

    ``policy`` is a spec for :func:`make_policy`, or a callable: a factory taking the env and
    returning ``policy(obs, info) -> action``, or such a policy itself."""

    policy: str | Callable
    scenarios: Sequence[str]
    episodes: int = 1
    seed: int = 0
    backend: str = "procedural"
    checkpoint: str | None = None
    config: dict | EnvConfig | None = None
    max_steps: int | None = None

    def __post_init__(self) -> None:
        if isinstance(self.scenarios, str):
            raise ValueError(f"scenarios must be a list of scenario names or paths, got the string {self.scenarios!r}")
        object.__setattr__(self, "scenarios", tuple(self.scenarios))
        if isinstance(self.episodes, bool) or not isinstance(self.episodes, int) or self.episodes < 1:
            raise ValueError(f"episodes must be a positive integer, got {self.episodes!r}")
        check_max_steps(self.max_steps)


def evaluate(request: EvalRequest, progress: bool = True) -> dict[str, Any]:
    """Run ``request``'s policy for its episodes on each of its scenarios (:class:`EvalRequest`);
    the report (:func:`build_report`). ``progress``: a bar per scenario."""
    import gymnasium as gym
    from tqdm import tqdm

    r = request
    results: list[tuple[str, list[dict[str, float]]]] = []
    for name in r.scenarios:
        scenario = load_scenario(name)
        env = gym.make("M4World-v0", scenario=scenario, backend=r.backend, checkpoint=r.checkpoint, config=r.config)
        episode_policy = scenario_policy(r.policy, env)
        eps = [
            run_episode(env, episode_policy, seed=r.seed + e, max_steps=r.max_steps)
            for e in tqdm(range(r.episodes), desc=scenario.name, unit="ep", disable=not progress)
        ]
        env.close()
        results.append((scenario.name, eps))
    return build_report(r, results)


def check_max_steps(max_steps: int | None) -> None:
    if max_steps is not None and (isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1):
        raise ValueError(f"max_steps must be a positive integer or None (the whole episode), got {max_steps!r}")


def scenario_policy(policy: str | Callable, env: gym.Env) -> Policy | str:
    """What :func:`run_episode` runs on ``env`` for every episode of a scenario: a built-in name stays a
    name (built per episode), a spec or factory is built once for the env, a policy is itself."""
    if callable(policy):
        return policy(env) if list(inspect.signature(policy).parameters) == ["env"] else policy
    return policy if is_named_policy(policy) else make_policy(policy, env)


def build_report(request: EvalRequest, results: Sequence[tuple[str, Sequence[dict[str, float]]]]) -> dict[str, Any]:
    """The report of ``request``'s evaluation: ``results`` holds each scenario's name and its
    episodes' metrics in episode order."""
    records = [{"scenario": name, "episode": e, **m} for name, eps in results for e, m in enumerate(eps)]
    policy = request.policy
    return {
        "policy": policy if isinstance(policy, str) else getattr(policy, "__qualname__", repr(policy)),
        "backend": request.backend,
        "seed": request.seed,
        "per_scenario": {name: aggregate(eps) for name, eps in results},
        "overall": aggregate(records),
        "episodes": records,
    }


def format_table(report: dict[str, Any]) -> str:
    """A plain-text table of the per-scenario and overall figures; with route-scored (log-replay)
    scenarios, an ``off_route`` column too ("-" where a scenario has no route)."""
    cols = ("collision", "off_road", "progress", "ttc_violation", "comfort", "pdms", "episodes")
    if any("off_route" in agg for agg in report["per_scenario"].values()):
        cols = (*cols[:2], "off_route", *cols[2:])

    def cell(agg: dict[str, float], c: str) -> str:
        if c == "episodes":
            return f"{int(agg[c])}"
        return f"{agg[c]:.3f}" if c in agg else "-"

    rows = [("scenario", *cols)]
    for name, agg in [*report["per_scenario"].items(), ("OVERALL", report["overall"])]:
        rows.append((name, *(cell(agg, c) for c in cols)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def write_report(report: dict[str, Any], path: str | Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=1, default=float))
