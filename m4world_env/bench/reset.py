"""What a scenario's completion adapters cost ``reset()`` on the world-model backend.

A completion adapter (``world_model.lora.AdapterInfo.completes``) adds one reference-model sample
at reset when its category is in the first frame (``WorldModel.first_frame``). This times
``env.reset(seed=r)`` of one scenario with its adapters as listed and with the completion adapters
left out, in interleaved rounds (the shared machine's speed drifts; the order alternates), and
reports the medians and their ratio; the first round (loading, allocator warm-up) is left out of
the medians.

    m4world bench reset [--scenario tree_truck_highway] [--rounds 5] --out FILE.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from m4world_env.env import M4WorldEnv
from m4world_env.scenario import load_scenario
from world_model.bundle import resolve_bundle
from world_model.lora import read_adapter, resolve_adapter


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="m4world bench reset", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="tree_truck_highway")
    ap.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.rounds < 2:
        ap.error("--rounds must be >= 2 (the first round is warm-up)")
    scenario = load_scenario(a.scenario)
    search = [resolve_bundle(a.checkpoint) / "adapters"]  # where the env looks first
    completing = [n for n in scenario.adapters if read_adapter(resolve_adapter(n, search))[0].completes]
    if not completing:
        ap.error(f"scenario {a.scenario!r} names no completion adapter (its adapters: {scenario.adapters})")
    variants = {
        "with_completion": list(scenario.adapters),
        "without_completion": [n for n in scenario.adapters if n not in completing],
    }
    envs = {
        name: M4WorldEnv(
            scenario.model_copy(update={"adapters": adapters}), backend="world_model", checkpoint=a.checkpoint
        )
        for name, adapters in variants.items()
    }
    seconds: dict[str, list[float]] = {name: [] for name in envs}
    for r in range(a.rounds):
        for name, env in sorted(envs.items(), reverse=r % 2 == 1):  # each variant first in every other round
            t0 = time.perf_counter()
            env.reset(seed=r)
            seconds[name].append(time.perf_counter() - t0)
    out = {
        "scenario": a.scenario,
        "checkpoint": a.checkpoint,
        "completion_adapters": completing,
        "rounds": a.rounds,
        **{f"{name}_s": statistics.median(s[1:]) for name, s in seconds.items()},
        "per_round_s": seconds,
    }
    out["ratio"] = out["with_completion_s"] / out["without_completion_s"]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1))
    print(
        f"{a.scenario}: reset() {out['with_completion_s']:.2f} s with {completing}, "
        f"{out['without_completion_s']:.2f} s without ({out['ratio']:.2f}x); wrote {a.out}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
