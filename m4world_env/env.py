"""``M4World-v0``: a Gymnasium env whose observations are multi-view cameras + LiDAR.

Each ``step(action)`` applies the ego action and the scenario's traffic for one policy step (one
causal chunk of ``sensor_frequency / policy_frequency`` frames) and returns the sensors of the
newest frame, rendered by the chosen backend. Rewards and termination come from the traffic
state, highway-env style (:mod:`m4world_env.rewards`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded

from m4world_env.backends import SensorBackend, make_backend
from m4world_env.config import BACKENDS, EnvConfig, InvalidOptionError, UnknownOptionError
from m4world_env.metrics import EpisodeMetrics
from m4world_env.rewards import combine_reward, reward_terms
from m4world_env.scenario import Scenario, load_scenario
from m4world_env.traffic import ActionError, TrafficBridge  # noqa: F401 (ActionError: part of the env API)
from m4world_env.traffic.polyline import Polyline
from world_model.geometry import world_to_ego_xy, wrap_angle
from world_model.observation import SENSOR_NAMES, Observation, SensorSelection
from world_model.scene import SceneFrame
from world_model.sensors import BevSpec, LidarSpec, default_rig

STATE_FEATURES = ("presence", "x", "y", "vx", "vy", "cos_yaw", "sin_yaw", "length", "width")
RESET_OPTIONS = ("reference",)
# rgb_array: the newest frame's mosaic (render_fps = policy frequency, one per step);
# rgb_array_list: every sensor frame's mosaic since the last render() (render_fps = sensor frequency).
RENDER_MODES = ("rgb_array", "rgb_array_list")
BACKEND_METHODS = ("reset", "reset_many", "step")  # what a shared backend must offer (SensorBackend)


def check_render_mode(render_mode: object) -> None:
    """Refuse a ``render_mode`` that is neither None nor one of :data:`RENDER_MODES`."""
    if render_mode is not None and not (isinstance(render_mode, str) and render_mode in RENDER_MODES):
        raise InvalidOptionError(f"render_mode must be one of {list(RENDER_MODES)} or None, got {render_mode!r}")


class _RenderModes(list):
    """The env's ``metadata["render_modes"]``. ``gymnasium.make`` looks a requested mode up here
    before it builds the env and, for a mode that is not a string, then fails inside itself
    (``mode.endswith``): such a mode is refused here, by name, instead."""

    def __contains__(self, mode: object) -> bool:
        if mode is not None and not isinstance(mode, str):
            check_render_mode(mode)
        return super().__contains__(mode)


def check_seed(seed: object, name: str = "reset(seed=...)") -> int | None:
    """``seed`` as a Python int (numpy integers accepted), or None; a bool, a float, a negative
    number or anything else is refused by ``name``."""
    if seed is None:
        return None
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise InvalidOptionError(f"{name} must be a non-negative integer or None, got {seed!r}")
    return int(seed)


def _reset_options(options: Any) -> dict[str, Any]:
    """``reset(options=...)`` as a dict, refusing what is not one before any work is done."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise TypeError(f"reset options must be a dict such as {{'reference': ...}}, got {type(options).__name__}")
    bad = [k for k in options if not isinstance(k, str)]
    if bad:
        raise TypeError(f"reset option names must be strings, got {bad!r}")
    reference = options.get("reference")
    if reference is not None and not isinstance(reference, Mapping):
        raise TypeError(
            "reset option 'reference' must be a dict of images by view, such as {'FRONT': image}, "
            f"{{'cameras': images}} or {{'lidar': ranges}}, got {type(reference).__name__}"
        )
    return dict(options)


STATE_BOUND = 1.0e4  # metres / m/s; values are clipped to it (roads are at most a few km long)


def state_from_frame(frame: SceneFrame, n_objects: int) -> np.ndarray:
    """highway-env Kinematics-style state: row 0 the ego, then the nearest objects, ego frame.

    Returns float32 (1 + n_objects, len(STATE_FEATURES)); absent rows are all zero.
    """
    out = np.zeros((1 + n_objects, len(STATE_FEATURES)), dtype=np.float32)
    ego = frame.ego
    out[0] = (1.0, 0.0, 0.0, ego.speed, 0.0, 1.0, 0.0, ego.size[0], ego.size[1])
    if not frame.objects:
        return out
    ego_xy = np.array([ego.x, ego.y])
    centers = world_to_ego_xy(np.array([o.box.center[:2] for o in frame.objects]), ego_xy, ego.yaw)
    vel = world_to_ego_xy(np.array([o.velocity for o in frame.objects]), np.zeros(2), ego.yaw)
    order = np.argsort(np.hypot(centers[:, 0], centers[:, 1]), kind="stable")[:n_objects]
    for row, i in enumerate(order, start=1):
        o = frame.objects[i]
        rel_yaw = float(wrap_angle(o.box.yaw - ego.yaw))
        out[row] = (1.0, *centers[i], *vel[i], np.cos(rel_yaw), np.sin(rel_yaw), o.box.size[0], o.box.size[1])
    return out


def observation_dict(keys: tuple[str, ...], obs: Observation, state: np.ndarray | None) -> dict[str, np.ndarray]:
    """The env's observation of ``keys`` from the sensors ``obs`` and the ``state`` array (None
    when ``keys`` lacks "state"); a sensor of ``keys`` that ``obs`` lacks (not decoded) raises
    :class:`~world_model.observation.SensorNotDecoded`."""
    sensors = {"bev": obs.bev, "state": state}
    sensors |= {name: obs.sensor(name) for name in SENSOR_NAMES if name in keys}
    return {k: v for k, v in sensors.items() if k in keys}


def decoded_sensors(observation_keys: tuple[str, ...], render_mode: str | None) -> SensorSelection:
    """The sensors a world-model env decodes: those its ``observation_keys`` name, and both when it
    renders (the mosaic shows the cameras and the LiDAR)."""
    rendering = render_mode is not None
    return SensorSelection(**{name: name in observation_keys or rendering for name in SENSOR_NAMES})


def _check_shared_backend(shared_backend: object, backend_index: object) -> None:
    """Refuse a ``shared_backend`` that is not a sensor backend, and a ``backend_index`` that names
    no row of it."""
    if shared_backend is not None and not all(callable(getattr(shared_backend, m, None)) for m in BACKEND_METHODS):
        raise InvalidOptionError(
            f"shared_backend must be None or a sensor backend with methods {BACKEND_METHODS} (the vector env "
            f"passes its own; users leave it unset), got {type(shared_backend).__name__} {shared_backend!r}"
        )
    if isinstance(backend_index, bool) or not isinstance(backend_index, numbers.Integral) or backend_index < 0:
        raise InvalidOptionError(f"backend_index must be a non-negative integer, got {backend_index!r}")
    if shared_backend is None and backend_index != 0:
        raise InvalidOptionError(
            f"backend_index={backend_index!r} names a rollout of a shared_backend; without one it must be 0"
        )


class M4WorldEnv(gym.Env):
    """The M4World driving env. See the README for options; ``config`` keys in :class:`EnvConfig`."""

    metadata = {"render_modes": _RenderModes(RENDER_MODES), "render_fps": 10}

    def __init__(
        self,
        scenario: str | Scenario = "highway_sunny_day",
        backend: str = "procedural",
        checkpoint: str | None = None,
        render_mode: str | None = None,
        config: dict[str, Any] | EnvConfig | None = None,
        shared_backend: SensorBackend | None = None,
        backend_index: int = 0,
    ) -> None:
        """``shared_backend``/``backend_index`` are for :class:`M4WorldVectorEnv`, which batches one
        backend over its sub-envs; users leave them unset."""
        if backend not in BACKENDS:
            raise InvalidOptionError(f"backend must be one of {BACKENDS}, got {backend!r}")
        check_render_mode(render_mode)
        _check_shared_backend(shared_backend, backend_index)
        self.cfg = config if isinstance(config, EnvConfig) else EnvConfig.from_dict(config)
        if self.cfg.workers and shared_backend is None:
            raise InvalidOptionError(
                f"config.workers={self.cfg.workers} runs a vector env's sub-envs in worker processes; a single env "
                "has none: use gym.make_vec(..., vectorization_mode='vector_entry_point') or leave workers at 0"
            )
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.render_mode = render_mode
        every_frame = render_mode == "rgb_array_list"  # the backend then observes each frame of a chunk
        self.backend_name = backend
        self.backend: SensorBackend = shared_backend or make_backend(
            backend,
            checkpoint,
            num_rollouts=1,
            with_bev=self.needs_bev,
            config=self.cfg,
            every_frame=every_frame,
            sensors=self.decoded_sensors,
        )
        self.backend_index = backend_index
        if self.scenario.adapters and hasattr(self.backend, "apply_adapters"):
            # Long-tail LoRA adapters named by the scenario (§5); the procedural backend renders
            # ground truth and needs none.
            self.backend.apply_adapters(self.scenario.adapters)
        # The world model fixes its own sensors (the checkpoint's); the procedural rig is configurable.
        model_cfg = getattr(self.backend, "model_cfg", None)
        if model_cfg is not None:
            self.rig, self.lidar_spec, self.bev_spec = self.backend.rig, model_cfg.sensors.lidar, model_cfg.sensors.bev
            chunk = model_cfg.clip.chunk_frames
            if self.scenario.frames_per_step % chunk:
                raise InvalidOptionError(
                    f"scenario {self.scenario.name!r}: a step spans {self.scenario.frames_per_step} sensor frame(s) "
                    f"(sensor_frequency / policy_frequency), not a multiple of the checkpoint's {chunk}-frame chunks; "
                    f"choose frequencies whose ratio is a multiple of {chunk} for backend='world_model'"
                )
        else:
            self.rig = default_rig(width=self.cfg.width, height=self.cfg.height)
            self.lidar_spec, self.bev_spec = LidarSpec(), BevSpec()
        self.bridge = TrafficBridge(
            self.scenario, action_type=self.cfg.action_type, rig=self.rig, lidar=self.lidar_spec, bev=self.bev_spec
        )
        fps = self.scenario.sensor_frequency if every_frame else self.scenario.policy_frequency
        self.metadata = {**self.metadata, "render_fps": fps}
        self.action_space = self._make_action_space()
        self.observation_space = self._make_observation_space()
        self._frame: SceneFrame | None = None
        self._obs: Observation | None = None
        self._unrendered: list[tuple[SceneFrame, Observation]] = []  # rgb_array_list's frames to come
        self._needs_reset = True
        self._metrics: EpisodeMetrics | None = None

    # -- construction helpers --

    @property
    def needs_bev(self) -> bool:
        """Whether observations must carry the BEV raster (an observation key, or the render mosaic)."""
        return "bev" in self.cfg.observation_keys or self.render_mode is not None

    @property
    def decoded_sensors(self) -> SensorSelection:
        """The sensors the world model decodes (:func:`decoded_sensors`)."""
        return decoded_sensors(self.cfg.observation_keys, self.render_mode)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return self.rig.names

    def _make_action_space(self) -> spaces.Space:
        if self.cfg.action_type == "continuous":
            return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        return spaces.Discrete(5)

    def _make_observation_space(self) -> spaces.Dict:
        h, w = self.rig.resolution
        bh, bw, bc = self.bev_spec.shape
        all_spaces = {
            "cameras": spaces.Box(0, 255, shape=(self.rig.num_views, h, w, 3), dtype=np.uint8),
            "lidar": spaces.Box(
                0.0, self.lidar_spec.max_range, shape=(self.lidar_spec.beams, self.lidar_spec.azimuth), dtype=np.float32
            ),
            "bev": spaces.Box(0, 1, shape=(bh, bw, bc), dtype=np.uint8),
            "state": spaces.Box(
                -STATE_BOUND, STATE_BOUND, shape=(1 + self.cfg.state_objects, len(STATE_FEATURES)), dtype=np.float32
            ),
        }
        return spaces.Dict({k: all_spaces[k] for k in self.cfg.observation_keys})

    # -- gymnasium API --

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        frame, options, model_seed = self.begin_reset(seed=seed, options=options)
        return self.finish_reset(self.backend.reset(self.backend_index, frame, options, model_seed))

    def begin_reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[SceneFrame, dict, int]:
        """First half of :meth:`reset`: seed, check the options, reset the traffic. Returns the first
        SceneFrame, the options and the backend's seed (the vector env samples the first frames of
        several sub-envs in one backend call, then calls :meth:`finish_reset` on each)."""
        super().reset(seed=check_seed(seed))
        # Until this reset succeeds the env holds no valid episode: a failed reset (e.g. a bad
        # reference image) leaves it asking for another reset rather than half-reset.
        self._needs_reset = True
        options = _reset_options(options)
        unknown = set(options) - set(RESET_OPTIONS)
        if unknown:
            raise UnknownOptionError(f"unknown reset option(s) {sorted(unknown)}; valid: {list(RESET_OPTIONS)}")
        bridge_seed = int(self.np_random.integers(0, 2**31 - 1))
        self._frame = self.bridge.reset(seed=bridge_seed)
        model_seed = int(self.np_random.integers(0, 2**31 - 1))
        return self._frame, options, model_seed

    def finish_reset(self, first: Observation) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Second half of :meth:`reset`, given the backend's first observation."""
        self._obs = first
        self._unrendered = [(self._frame, self._obs)] if self.render_mode == "rgb_array_list" else []
        info = self.start_episode()
        return self._observation(), info

    def start_episode(self) -> dict[str, Any]:
        """The sensor-free part of :meth:`finish_reset`: the episode starts at the frame
        :meth:`begin_reset` returned; returns the reset's info. (A simulation worker calls it where
        the sensors come from another process, :mod:`m4world_env.workers`.)"""
        road = self.scenario.road
        self._metrics = EpisodeMetrics(
            dt=1.0 / self.scenario.sensor_frequency,
            reference_speed=road.speed_limit,
            route=Polyline.from_points(road.reference_path) if road.type == "route" else None,
        )
        self._metrics.add_frame(self._frame)
        self._needs_reset = False
        return self._info({})

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        frames = self.advance(action)
        (observations,) = self.backend.step([frames])
        return self.finish_step(frames, observations)

    def _require_episode(self) -> None:
        if self._needs_reset:
            raise ResetNeeded(
                "call env.reset() before env.step() (the episode ended, never started, or the last reset failed)"
            )

    def check_action(self, action: Any) -> None:
        """Raise :class:`ResetNeeded` or :class:`ActionError` if :meth:`step` would refuse ``action``;
        changes nothing (the vector env checks every sub-env's action before advancing any)."""
        self._require_episode()
        self.bridge.parse_action(action)  # highway-env's ranges

    def advance(self, action: Any) -> list[SceneFrame]:
        """First half of a step: validate the action and run the traffic for one chunk."""
        self._require_episode()
        return self.bridge.step(action)  # parses the action (ActionError) before touching any state

    def finish_step(
        self, frames: list[SceneFrame], observations: list[Observation]
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Second half of a step: given the chunk's observations, compute reward, flags and info."""
        self._obs = observations[-1]
        if self.render_mode == "rgb_array_list":
            self._unrendered += zip(frames, observations, strict=True)
        reward, terminated, truncated, info = self.settle_step(frames)
        return self._observation(), reward, terminated, truncated, info

    def settle_step(self, frames: list[SceneFrame]) -> tuple[float, bool, bool, dict[str, Any]]:
        """The sensor-free part of :meth:`finish_step`: the step's reward, terminated, truncated and
        info from the traffic's ``frames`` (what :meth:`advance` returned)."""
        previous = self._frame
        self._frame = frames[-1]
        for fr in frames:
            self._metrics.add_frame(fr)
        terms = self._reward_terms(previous, frames)
        reward = combine_reward(terms, self.cfg.reward)
        if not math.isfinite(reward):  # the config bounds the weights; this names a bug, never returns NaN
            raise RuntimeError(f"the reward came out non-finite ({reward}) from the terms {terms}")
        crashed, on_road = bool(self.bridge.crashed), bool(self.bridge.on_road)
        self._metrics.add_step(reward, crashed, on_road)
        terminated = crashed or (self.cfg.offroad_terminal and not on_road)
        truncated = bool(self.bridge.truncated) and not terminated
        self._needs_reset = terminated or truncated
        return reward, terminated, truncated, self._info(terms)

    def render(self) -> np.ndarray | list[np.ndarray] | None:
        """The mosaic (all views, LiDAR, BEV) of the newest sensor frame; with
        ``render_mode="rgb_array_list"`` the mosaics of every sensor frame since the last call."""
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array' to gym.make")
            return None
        from world_model.sim import mosaic

        if self._obs is None:
            raise ResetNeeded("call env.reset() before env.render()")
        if self.render_mode == "rgb_array_list":
            frames, self._unrendered = self._unrendered, []
            return [mosaic(obs, frame) for frame, obs in frames]
        return mosaic(self._obs, self._frame)

    # -- interactive object manipulation (the paper's "M"anipulation) --

    def insert_object(self, spec: dict[str, Any]) -> str:
        """Add an object (scenario ``objects`` entry syntax); it appears from the next step. Returns its id."""
        return self.bridge.insert_object(spec)

    def remove_object(self, track_id: str) -> None:
        """Remove an object (scripted or IDM traffic) by track id, from the next step on."""
        self.bridge.remove_object(track_id)

    def edit_object(self, track_id: str, **changes: Any) -> None:
        """Change an object's category, colour, description, image or track from the next step on."""
        self.bridge.edit_object(track_id, **changes)

    # -- internals --

    def _reward_terms(self, previous: SceneFrame, frames: list[SceneFrame]) -> dict[str, float]:
        """Terms of the step from ``previous`` (the last frame before it) through ``frames``."""
        dt = len(frames) / self.scenario.sensor_frequency
        ego = self.bridge.ego
        progress = float(np.hypot(ego.x - previous.ego.x, ego.y - previous.ego.y))
        return reward_terms(
            crashed=bool(self.bridge.crashed),
            speed=float(ego.speed),
            lane_index=int(self.bridge.lane_index[2]),
            num_lanes=int(self.bridge.num_lanes),
            on_road=bool(self.bridge.on_road),
            progress_m=progress,
            max_progress_m=self.scenario.road.speed_limit * dt,
            cfg=self.cfg.reward,
        )

    @property
    def scene_frame(self) -> SceneFrame:
        """The scene the last observation shows (the last sensor frame of the last reset or step,
        also after the episode ended)."""
        if self._frame is None:
            raise ResetNeeded("call env.reset() first: no scene yet")
        return self._frame

    def state_observation(self) -> np.ndarray:
        """The ``state`` observation of the newest frame (:func:`state_from_frame`, clipped)."""
        return np.clip(state_from_frame(self._frame, self.cfg.state_objects), -STATE_BOUND, STATE_BOUND)

    def _observation(self) -> dict[str, np.ndarray]:
        state = self.state_observation() if "state" in self.cfg.observation_keys else None
        return observation_dict(self.cfg.observation_keys, self._obs, state)

    def _info(self, terms: dict[str, float]) -> dict[str, Any]:
        ego = self.bridge.ego
        return {
            "time": float(self.bridge.time),
            "speed": float(ego.speed),
            "crashed": bool(self.bridge.crashed),
            "on_road": bool(self.bridge.on_road),
            "end_of_road": bool(self.bridge.end_of_road),
            "lane_index": int(self.bridge.lane_index[2]),
            # What the road is made from: a route road's map or logged path, else the scenario's road.
            "road_source": getattr(self.scenario.road, "source", "scenario"),
            "rewards": dict(terms),
            "episode_metrics": self._metrics.summary(),
        }
