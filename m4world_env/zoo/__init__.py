"""A zoo of driving policies that see: each drives from the env's cameras and LiDAR and the ego's
own speed alone, never from the traffic state, so its score tells one sensor backend from another.

Three families (:data:`~m4world_env.zoo.base.FAMILIES`): ``modular`` (LiDAR gap keeping and camera
lane centring with parameter variants, :mod:`m4world_env.zoo.modular`), ``learned`` (small CNNs
behaviour-cloned from the autopilot, :mod:`m4world_env.zoo.learned`; ``make zoo`` retrains them) and
``perturbed`` (a modular driver with noisy, late or blinded sensors, :mod:`m4world_env.zoo.perturbed`).

    import gymnasium as gym, m4world_env
    from m4world_env import zoo

    env = gym.make("M4World-v0", scenario="highway_sunny_day", backend="world_model")
    obs, info = env.reset(seed=0)
    policy = zoo.member("gap_keeper").build(zoo.SensorGeometry.of_env(env), seed=0)
    obs, reward, terminated, truncated, info = env.step(policy(obs, info))

From the command line: ``m4world eval --policy gap_keeper`` scores one member;
``m4world agreement`` scores them all on both backends (:mod:`m4world_env.agreement`).
"""

from __future__ import annotations

import functools

from m4world_env.zoo.base import (
    EGO_STATUS_KEYS,
    FAMILIES,
    SENSOR_KEYS,
    EgoStatus,
    SensorGeometry,
    SensorPolicy,
    ZooMember,
)
from m4world_env.zoo.learned import learned_members
from m4world_env.zoo.registry import rule_members

__all__ = [
    "EGO_STATUS_KEYS",
    "FAMILIES",
    "SENSOR_KEYS",
    "EgoStatus",
    "SensorGeometry",
    "SensorPolicy",
    "ZooMember",
    "member",
    "members",
]


@functools.cache
def members() -> dict[str, ZooMember]:
    """Every zoo member by name, modular first, then learned, then perturbed."""
    everyone = rule_members() + learned_members()
    order = {family: i for i, family in enumerate(FAMILIES)}
    everyone.sort(key=lambda m: order[m.family])  # stable: each family keeps its own order
    named = {m.name: m for m in everyone}
    if len(named) != len(everyone):
        raise RuntimeError("two zoo members share a name")
    return named


def member(name: str) -> ZooMember:
    """The zoo member ``name`` (a ``name@vN`` citation is accepted when N is its version)."""
    base, _, version = name.partition("@v")
    found = members().get(base)
    if found is None:
        raise ValueError(f"unknown zoo policy {name!r}; the zoo has {list(members())}")
    if version and version != str(found.version):
        raise ValueError(f"zoo policy {base!r} is at version {found.version}, not {version!r}")
    return found
