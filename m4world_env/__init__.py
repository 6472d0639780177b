"""M4World-Gym: Gymnasium environments whose dynamics are the M4World world model.

``import m4world_env`` registers ``M4World-v0`` (single env) with a ``vector_entry_point`` for the
batched vector env.
"""

from gymnasium.envs.registration import register, registry

ENV_ID = "M4World-v0"

if ENV_ID not in registry:
    register(
        id=ENV_ID,
        entry_point="m4world_env.env:M4WorldEnv",
        vector_entry_point="m4world_env.vector:M4WorldVectorEnv",
    )

__all__ = ["ENV_ID"]
