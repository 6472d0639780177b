"""Precompute a checkpoint's text embeddings for a set of episodes, for a machine that cannot
install its text encoder (an offline GPU node without the MiniLM weights).

    m4world text-embeddings --scenario highway_sunny_day --episodes 64 --out text_embeddings.npz
    M4WORLD_TEXT_EMBEDDINGS=text_embeddings.npz python ...    # on the other machine

The texts a world-model rollout encodes are its scene prompt, the category names and the
descriptions of the objects it meets; they come from the traffic alone, so the episodes are run
here without sensors, with the lane-keeping reference policy (the objects met depend on where the
ego drives: another policy may meet others). Seeds ``seed .. seed + episodes - 1`` cover a
vector env of that many envs reset with ``seed``. On the other machine a text the file lacks
raises a ``KeyError`` naming it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from m4world_env.env import M4WorldEnv
from m4world_env.policies import ConstantSpeedLaneKeeping
from world_model.bundle import load_bundle_files
from world_model.model.conditions import condition_texts
from world_model.model.config import ModelConfig
from world_model.model.text import TEXT_EMBEDDINGS_VARIABLE, make_text_encoder, save_text_embeddings


def precompute_text_embeddings(
    scenarios: Sequence[str],
    out: str | Path,
    episodes: int = 1,
    seed: int = 0,
    steps: int | None = None,
    checkpoint: str | None = None,
) -> tuple[Path, int, int]:
    """Encode the texts of ``episodes`` episodes of each scenario (at most ``steps`` steps each;
    None: to the end) with ``checkpoint``'s text encoder (default: the shipped bundle's) and write
    them to ``out``. Returns the file and the numbers of token-level and pooled texts."""
    if os.environ.get(TEXT_EMBEDDINGS_VARIABLE):
        raise RuntimeError(
            f"${TEXT_EMBEDDINGS_VARIABLE} is set: unset it to compute embeddings with the text encoder itself"
        )
    if episodes < 1 or (steps is not None and steps < 0):
        raise ValueError(f"need episodes >= 1 and steps >= 0, got {episodes} and {steps}")
    text_cfg = ModelConfig.from_dict(load_bundle_files(checkpoint).model_config).text
    encoder = make_text_encoder(text_cfg)
    prompts: set[str] = set()
    pooled: set[str] = set()
    for scenario in scenarios:
        env = M4WorldEnv(scenario, backend="procedural", config={"observation_keys": ["lidar"]})
        for episode_seed in range(seed, seed + episodes):
            env.reset(seed=episode_seed)
            policy, step = ConstantSpeedLaneKeeping(), 0
            frames = [env._frame]  # the reset frame
            while steps is None or step < steps:
                frames += env.advance(policy(env.bridge))
                step += 1
                if env.bridge.crashed or env.bridge.truncated:
                    break
            p, o = condition_texts(frames)
            prompts |= p
            pooled |= o
        env.close()
    for text in sorted(prompts):
        encoder.tokens(text)
    encoder.pooled(sorted(pooled))
    return save_text_embeddings(encoder, text_cfg.encoder, out), len(prompts), len(pooled)
