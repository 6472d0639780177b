"""Train PPO (Stable-Baselines3) over a RayVectorEnv and score it with the harness on Ray.

    python examples/train_sb3_ray.py --num-envs 8 --workers 4 --timesteps 20000 --out out/ppo_ray
    python examples/train_sb3_ray.py --address auto ...    # on a running Ray cluster (ray start)
    python examples/train_sb3_ray.py --num-envs 2 --workers 2 --timesteps 64 --height 40 --width 72  # smoke test

The sub-envs run in ``--workers`` Ray actors, each a batched vector env of its share
(:class:`m4world_env.cluster.RayVectorEnv`); :class:`m4world_env.sb3.SB3VecEnv` presents them to SB3
with the observations of :class:`m4world_env.wrappers.SB3Observations` (as examples/train_ppo.py).
After training, :func:`m4world_env.cluster.evaluate_on_ray` scores the saved policy on fresh seeds;
each worker loads it from ``--out``, so on several nodes ``--out`` must be on a shared file system.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from stable_baselines3 import PPO

from m4world_env.cluster import RayVectorEnv, connect, evaluate_on_ray, require_ray
from m4world_env.evaluate import EvalRequest, format_table
from m4world_env.sb3 import SB3VecEnv
from m4world_env.wrappers import SB3ObservationMap


def saved_policy(model_path: str):
    """A harness policy factory (``factory(env) -> policy(obs, info)``) that loads the saved PPO model
    where it runs: only the path travels to the Ray workers."""

    def factory(env):
        model = PPO.load(model_path, device="cpu")
        observation_map = SB3ObservationMap(env.observation_space)
        return lambda obs, info: model.predict(observation_map(obs), deterministic=True)[0]

    return factory


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="highway_sunny_day")
    ap.add_argument("--backend", default="procedural")
    ap.add_argument("--address", default=None, help="Ray address (default: RAY_ADDRESS or a new local instance)")
    ap.add_argument("--timesteps", type=int, default=20_000)
    ap.add_argument("--num-envs", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--height", type=int, default=64)
    ap.add_argument("--width", type=int, default=112)
    ap.add_argument("--eval-episodes", type=int, default=2)
    ap.add_argument("--eval-max-steps", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("out/ppo_ray"))
    args = ap.parse_args(argv)

    config = {"observation_keys": ["cameras", "lidar", "state"], "height": args.height, "width": args.width}
    owns_ray = connect(args.address)  # one connection for training and scoring
    try:
        ray_venv = RayVectorEnv(
            args.num_envs, workers=args.workers, scenario=args.scenario, backend=args.backend, config=config
        )
        venv = SB3VecEnv(ray_venv)
        venv.seed(args.seed)  # sub-env i seeded seed + i
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
        venv.close()  # frees the actors' CPUs for the evaluation's workers
        args.out.mkdir(parents=True, exist_ok=True)
        model.save(args.out / "ppo_m4world")

        request = EvalRequest(
            saved_policy(str((args.out / "ppo_m4world.zip").resolve())),
            [args.scenario],
            episodes=args.eval_episodes,
            seed=10_000 + args.seed,
            backend=args.backend,
            config=config,
            max_steps=args.eval_max_steps,
        )
        report = evaluate_on_ray(request, progress=False, workers=args.workers)
    finally:
        if owns_ray:
            require_ray().shutdown()
    print(format_table(report))
    (args.out / "eval.json").write_text(json.dumps(report, indent=1, default=float))
    return {**report, "timesteps": model.num_timesteps}


if __name__ == "__main__":
    main()
