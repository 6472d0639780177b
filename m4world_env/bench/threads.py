"""Torch threads under CPU contention: wall time of a world-model episode per thread setting.

Each setting runs in a fresh process (thread pools are fixed at the first torch call), while a
competitor process keeps the cores busy with torch matmuls (its own default threads), as when
several env processes share a machine::

    m4world bench threads --steps 20 --repeats 2 --out out/bench_threads.json
    m4world bench threads --num-envs 8 --steps 5 --out F.json    # a batched vector env of 8

Settings: ``default`` (``config.model.threads=None``: torch's own choice, one thread per core),
``torch1`` (``config.model.threads=1``: ``torch.set_num_threads(1)``, the rollouts in one group),
``omp1`` (``threads=None`` with ``OMP_NUM_THREADS=1`` in the environment, one group) and ``groups``
(the env's defaults: one torch thread, a vector env's rollouts in a group per core, each on a
thread of its own, ``config.model.rollout_threads``; a single env is one group).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

SETTINGS = ("default", "torch1", "omp1", "groups")

EPISODE = """
import sys, time, numpy as np, torch, gymnasium as gym
import m4world_env
setting, steps, num_envs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
# None: the process keeps torch's (or OMP's) choice; rollout groups None: one a core (of threads)
model = {"threads": 1 if setting in ("torch1", "groups") else None}
model["rollout_threads"] = 1 if setting in ("torch1", "omp1") else None
kw = dict(scenario="highway_sunny_day", backend="world_model", config={"model": model})
if num_envs == 1:
    env, action = gym.make("M4World-v0", **kw), np.zeros(2, np.float32)
else:
    env = gym.make_vec("M4World-v0", num_envs=num_envs, vectorization_mode="vector_entry_point", **kw)
    action = np.zeros((num_envs, 2), np.float32)
env.reset(seed=0)
start = time.perf_counter()
for _ in range(steps):
    env.step(action)
print(time.perf_counter() - start, torch.get_num_threads())
"""

COMPETITOR = """
import torch
a = torch.randn(512, 512)
while True:
    a = torch.tanh(a @ a)
"""


def run_episode(setting: str, steps: int, num_envs: int = 1) -> tuple[float, int]:
    env = dict(os.environ)
    env.pop("OMP_NUM_THREADS", None)
    if setting == "omp1":
        env["OMP_NUM_THREADS"] = "1"
    out = subprocess.run(
        [sys.executable, "-c", EPISODE, setting, str(steps), str(num_envs)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    seconds, threads = out.stdout.split()[-2:]
    return float(seconds), int(threads)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="m4world bench threads", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--num-envs", type=int, default=1, help="a batched vector env of N sub-envs (1: one env)")
    p.add_argument("--no-competitor", action="store_true", help="measure without the busy process")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    competitor = None if args.no_competitor else subprocess.Popen([sys.executable, "-c", COMPETITOR])
    rows = []
    try:
        time.sleep(0 if competitor is None else 2)
        for repeat in range(args.repeats):
            for setting in SETTINGS:
                seconds, threads = run_episode(setting, args.steps, args.num_envs)
                rows.append({"setting": setting, "repeat": repeat, "threads": threads, "episode_s": seconds})
                print(f"{setting:8s} repeat {repeat}: {threads} thread(s), {args.steps} steps in {seconds:.1f} s")
    finally:
        if competitor is not None:
            competitor.kill()
    result = {
        "steps": args.steps,
        "num_envs": args.num_envs,
        "cpus": os.cpu_count(),
        "competitor": competitor is not None,
        "rows": rows,
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
