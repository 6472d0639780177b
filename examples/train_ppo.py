"""Train PPO (Stable-Baselines3, MultiInputPolicy) on M4World and score it with the harness.

    python examples/train_ppo.py --scenario highway_sunny_day --timesteps 20000 --out out/ppo
    python examples/train_ppo.py --timesteps 256 --height 40 --width 72   # smoke test (CI does this)

Observations: the six cameras stacked on channels (a CNN branch), the LiDAR min-pooled per
azimuth sector and the kinematic state (MLP branches); see :class:`m4world_env.wrappers.SB3Observations`.
After training, the policy is scored by :func:`m4world_env.evaluate.evaluate` on the same scenario
with fresh seeds, and the table and JSON report are written next to the model.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env.evaluate import EvalRequest, evaluate, format_table
from m4world_env.wrappers import SB3Observations


def make_env(scenario: str, height: int, width: int, backend: str) -> gym.Env:
    config = {"observation_keys": ["cameras", "lidar", "state"], "height": height, "width": width}
    return SB3Observations(gym.make("M4World-v0", scenario=scenario, backend=backend, config=config))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="highway_sunny_day")
    ap.add_argument("--backend", default="procedural")
    ap.add_argument("--timesteps", type=int, default=20_000)
    ap.add_argument("--num-envs", type=int, default=2)
    ap.add_argument("--height", type=int, default=64)
    ap.add_argument("--width", type=int, default=112)
    ap.add_argument("--eval-episodes", type=int, default=2)
    ap.add_argument("--eval-max-steps", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("out/ppo"))
    args = ap.parse_args(argv)

    venv = make_vec_env(
        lambda: make_env(args.scenario, args.height, args.width, args.backend), n_envs=args.num_envs, seed=args.seed
    )
    n_steps = max(16, min(256, args.timesteps // args.num_envs))
    model = PPO(
        "MultiInputPolicy",
        venv,
        n_steps=n_steps,
        batch_size=min(64, n_steps * args.num_envs),
        n_epochs=4,
        learning_rate=3e-4,
        seed=args.seed,
        verbose=0,
        device="cpu",
    )
    model.learn(total_timesteps=args.timesteps, progress_bar=False)
    args.out.mkdir(parents=True, exist_ok=True)
    model.save(args.out / "ppo_m4world")

    wrapper = SB3Observations(
        gym.make(
            "M4World-v0",
            scenario=args.scenario,
            config={"observation_keys": ["cameras", "lidar", "state"], "height": args.height, "width": args.width},
        )
    )

    def policy_factory(env):  # the harness's env gives raw observations; wrap them like in training
        return lambda obs, info: model.predict(wrapper.observation(obs), deterministic=True)[0]

    request = EvalRequest(
        policy_factory,
        [args.scenario],
        episodes=args.eval_episodes,
        seed=10_000 + args.seed,
        backend=args.backend,
        max_steps=args.eval_max_steps,
        config={"observation_keys": ["cameras", "lidar", "state"], "height": args.height, "width": args.width},
    )
    report = evaluate(request, progress=False)
    print(format_table(report))
    (args.out / "eval.json").write_text(json.dumps(report, indent=1, default=float))
    return report


if __name__ == "__main__":
    main()
