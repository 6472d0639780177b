"""What a sensor policy may know, and the record that names a zoo member.

A zoo policy drives from the env's sensors alone: the cameras and the LiDAR of the observation,
plus the ego's own speed (what a car's own bus reports; NAVSIM gives its agents the same ego
status). It never reads other objects' states, the traffic bridge or ``info``'s traffic fields:
a policy that reads the traffic state scores the same on every backend by construction, so it
cannot tell a world model from the ground truth.

    geometry = SensorGeometry.of_env(env)           # the sensors' and actuators' specs, no traffic
    policy = zoo.member("gap_keeper").build(geometry, seed=0)
    action = policy(obs, info)                      # reads obs["cameras"], obs["lidar"], info["speed"]
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from world_model.observation import SENSOR_NAMES
from world_model.sensors import CameraRig, LidarSpec

# The one entry of an env's ``info`` a sensor policy may read: the ego's own speed (m/s).
EGO_STATUS_KEYS = ("speed",)
# The observation keys a sensor policy may see (an env's config observation_keys); never "state".
SENSOR_KEYS = SENSOR_NAMES
FAMILIES = ("modular", "learned", "perturbed")


@dataclass(frozen=True)
class EgoStatus:
    """The ego's own bus: its speed (m/s) and the acceleration since the previous step (m/s^2)."""

    speed: float
    acceleration: float = 0.0


@dataclass(frozen=True)
class SensorGeometry:
    """The car's own sensors and actuators: the camera rig, the LiDAR, the action ranges and the
    policy step. Everything a policy may know before it sees a frame; nothing of the traffic."""

    rig: CameraRig
    lidar: LidarSpec
    acceleration_range: tuple[float, float]  # m/s^2 at action[0] = -1 .. +1
    steering_range: tuple[float, float]  # front-wheel angle, rad, at action[1] = -1 .. +1 (+ turns right)
    step_seconds: float  # one policy step (1 / the scenario's policy frequency)

    @classmethod
    def of_env(cls, env: Any) -> SensorGeometry:
        """The geometry of a :class:`~m4world_env.env.M4WorldEnv` (or a wrapper of one) with
        continuous actions."""
        base = env.unwrapped
        if base.cfg.action_type != "continuous":
            raise ValueError(
                f"zoo policies steer and accelerate: they need config action_type='continuous', "
                f"got {base.cfg.action_type!r}"
            )
        actions = base.bridge.config.actions
        return cls(
            rig=base.rig,
            lidar=base.lidar_spec,
            acceleration_range=tuple(actions.acceleration_range),
            steering_range=tuple(actions.steering_range),
            step_seconds=1.0 / base.scenario.policy_frequency,
        )

    def view_index(self, name: str) -> int:
        """The position of camera ``name`` in the observation's view axis."""
        try:
            return self.rig.names.index(name)
        except ValueError:
            raise ValueError(f"the rig has no camera {name!r}; it has {list(self.rig.names)}") from None

    def action(self, acceleration: float, steering: float) -> np.ndarray:
        """The env's action for ``acceleration`` (m/s^2) and ``steering`` (rad, + turns right),
        clipped to the action space."""

        def unit(x: float, low_high: tuple[float, float]) -> float:
            low, high = low_high
            return min(1.0, max(-1.0, 2.0 * (x - low) / (high - low) - 1.0)) if math.isfinite(x) else 0.0

        return np.array(
            [unit(acceleration, self.acceleration_range), unit(steering, self.steering_range)], dtype=np.float32
        )

    def controls(self, action: np.ndarray) -> tuple[float, float]:
        """The inverse of :meth:`action`: (acceleration m/s^2, steering rad)."""

        def physical(u: float, low_high: tuple[float, float]) -> float:
            low, high = low_high
            return low + (float(u) + 1.0) * 0.5 * (high - low)

        return physical(action[0], self.acceleration_range), physical(action[1], self.steering_range)


class SensorPolicy:
    """Base of the zoo's policies: ``policy(obs, info) -> action`` that reads from ``info`` only
    :data:`EGO_STATUS_KEYS`. Subclasses implement :meth:`drive`. One instance drives one episode
    (it keeps what it saw before); build a fresh one per episode."""

    def __init__(self, geometry: SensorGeometry) -> None:
        self.geometry = geometry
        self._last_speed: float | None = None

    def __call__(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any]) -> np.ndarray:
        speed = float(info["speed"])
        previous, self._last_speed = self._last_speed, speed
        accel = 0.0 if previous is None else (speed - previous) / self.geometry.step_seconds
        sensors = {k: obs[k] for k in SENSOR_KEYS if k in obs}  # never "state", whatever the env's keys
        return self.drive(sensors, EgoStatus(speed=speed, acceleration=accel))

    def drive(self, obs: Mapping[str, np.ndarray], status: EgoStatus) -> np.ndarray:
        raise NotImplementedError


# Makes a member's policy for one episode from the car's geometry and the episode's seeds.
Builder = Callable[[SensorGeometry, np.random.SeedSequence], "SensorPolicy"]


@dataclass(frozen=True)
class ZooMember:
    """A named, versioned, seeded zoo policy. ``build(geometry, seed)`` makes a fresh policy for
    one episode; ``seed`` is the episode's (the member's own :attr:`seed` is mixed in, so two
    members never share noise)."""

    name: str
    family: str
    version: int
    seed: int
    description: str
    builder: Builder
    files: tuple[Path, ...] = ()  # what the member loads (its weights): part of a run's fingerprint

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ValueError(f"zoo member {self.name!r}: family must be one of {FAMILIES}, got {self.family!r}")

    @property
    def citation(self) -> str:
        """How a harness cites it: ``name@vVERSION``."""
        return f"{self.name}@v{self.version}"

    def build(self, geometry: SensorGeometry, seed: int = 0) -> SensorPolicy:
        return self.builder(geometry, np.random.SeedSequence([self.seed, int(seed)]))
