"""Digests of the env's observations on every bundled scenario, to show a refactor changes nothing.

Run before and after a change on the same machine and compare; any differing line names the
scenario, seed, step and observation key whose bytes changed::

    m4world bench digests --out before.json
    # ... change the code ...
    m4world bench digests --out after.json --compare before.json

Float rounding differs between CPUs (matrix kernels, vector widths), so digests are compared on one
machine only, never against stored values.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

DEFAULT_SEEDS = (0, 1, 2)
DEFAULT_STEPS = 3
# A fixed action sequence that brakes, accelerates and steers, so that the control tokens differ.
ACTIONS = ((0.3, 0.0), (-0.5, 0.2), (0.0, -0.1))


def _digest(value: np.ndarray) -> str:
    array = np.ascontiguousarray(value)
    header = f"{array.dtype.str}{array.shape}".encode()
    return hashlib.sha256(header + array.tobytes()).hexdigest()[:16]


def observation_digests(*, backend: str, scenarios: list[str], seeds: tuple[int, ...], steps: int) -> dict[str, str]:
    """``{"scenario/seed/step/key": digest}`` for ``reset`` (step 0) and ``steps`` steps."""
    import m4world_env
    from m4world_env.env import M4WorldEnv

    digests: dict[str, str] = {}
    for scenario in scenarios:
        for seed in seeds:
            env = M4WorldEnv(scenario=scenario, backend=backend)
            try:
                observation, _ = env.reset(seed=seed)
                for step in range(steps + 1):
                    if step:
                        action = np.asarray(ACTIONS[(step - 1) % len(ACTIONS)], np.float32)
                        observation, *_ = env.step(action)
                    for key in sorted(observation):
                        digests[f"{scenario}/{seed}/{step}/{key}"] = _digest(observation[key])
            finally:
                env.close()
            print(f"{scenario} seed {seed}: done", flush=True)
    del m4world_env
    return digests


def main(argv: list[str] | None = None) -> int:
    from m4world_env.scenario import list_scenarios

    parser = argparse.ArgumentParser(prog="m4world bench digests", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--compare", type=Path, help="an earlier run's file to compare with")
    parser.add_argument("--backend", default="world_model", choices=("world_model", "procedural"))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS))
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS)
    parser.add_argument("--scenarios", nargs="+", default=None)
    args = parser.parse_args(argv)
    scenarios = args.scenarios or list_scenarios()
    digests = observation_digests(backend=args.backend, scenarios=scenarios, seeds=tuple(args.seeds), steps=args.steps)
    args.out.write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
    if args.compare is None:
        return 0
    before = json.loads(args.compare.read_text())
    missing = sorted(key for key in digests if key not in before)
    if missing:
        print(f"{args.compare} has no digest of {len(missing)} of these observations, e.g. {missing[0]}")
        return 1
    differing = sorted(key for key in digests if before[key] != digests[key])
    for key in differing:
        print(f"differs: {key}")
    print(f"{len(digests) - len(differing)} of {len(digests)} observations identical")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
