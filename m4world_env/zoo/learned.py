"""The zoo's "learned" family: small CNNs behaviour-cloned from the IDM autopilot.

Each member sees the FRONT camera, the forward half of the LiDAR, or both, plus the ego's speed,
and outputs the env's continuous action. The members differ in their sensors and in how many
recorded autopilot episodes they were trained on (their data budget), so that the zoo holds
policies of clearly different quality whose ranking a world model must reproduce.

    geometry = SensorGeometry.of_env(env)
    policy = learned_member(LEARNED_SPECS[0]).build(geometry)
    action = policy(obs, info)

The weights are made by ``make zoo`` (:mod:`m4world_env.zoo.train_learned`) and shipped in
``m4world_env/zoo/weights/<member name>.safetensors``. :func:`extract_features` is the one place
that turns an observation into the network's inputs: the recorder and :class:`LearnedPolicy` both
call it.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load_file
from torch import nn

from m4world_env.zoo.base import EgoStatus, SensorGeometry, SensorPolicy, ZooMember

FAMILY = "learned"
SENSOR_SETS = ("cameras", "lidar", "both")
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
# Written into every weight file and checked on load: a file of another layout fails loudly.
WEIGHTS_FORMAT = "m4world-zoo-learned/1"

# -- the network's inputs --

CAMERA_VIEW = "FRONT"  # the lane ahead and the lead vehicle; the other views add little to a single-lane decision
# Half the rig's 64x112 in each direction: lane markings stay visible while the camera trunk stays small.
CAMERA_SHAPE = (32, 56)  # (height, width)
# The LiDAR's forward half, +90 deg (left) .. -90 deg (right): what is ahead and beside the ego.
LIDAR_FOV_FRACTION = 0.5
LIDAR_COLUMNS = 128  # the forward half (512 columns) min-pooled 4 to 1: the nearest return of each bin is kept
LIDAR_BEAMS = 32  # the rig's beam count; the network's LiDAR trunk is built for it
# m/s: the fastest bundled scenario's speed limit, so the speed input lies in about [0, 1].
SPEED_SCALE = 30.0


@dataclass(frozen=True)
class Features:
    """One observation as the network sees it.

    camera: float32 (3, 32, 56), the FRONT view downsampled, RGB in [0, 1];
    lidar: float32 (1, 32, 128), the forward half's ranges / max range, min-pooled, a ray without a
    return reads 1.0 (as far as the sensor sees, not 0 = touching the car);
    speed: float32 (1,), ego speed / :data:`SPEED_SCALE`.
    """

    camera: np.ndarray
    lidar: np.ndarray
    speed: np.ndarray


def lidar_columns(geometry: SensorGeometry) -> tuple[int, int]:
    """The [first, end) columns of the LiDAR range map that :func:`extract_features` keeps: the
    forward half, centred on straight ahead (column ``azimuth // 2``)."""
    azimuth = geometry.lidar.azimuth
    half = int(azimuth * LIDAR_FOV_FRACTION) // 2
    return azimuth // 2 - half, azimuth // 2 + half


def extract_features(obs: Mapping[str, np.ndarray], speed: float, geometry: SensorGeometry) -> Features:
    """The network's inputs from an env observation (needs ``obs["cameras"]`` and ``obs["lidar"]``)
    and the ego speed (m/s). A pure function: the same observation always gives the same arrays."""
    cameras, ranges = obs["cameras"], np.asarray(obs["lidar"], dtype=np.float32)
    spec = geometry.lidar
    first, end = lidar_columns(geometry)
    if ranges.shape != (LIDAR_BEAMS, spec.azimuth) or (end - first) % LIDAR_COLUMNS:
        raise ValueError(
            f"the learned policies need a {LIDAR_BEAMS}-beam LiDAR whose forward half divides into "
            f"{LIDAR_COLUMNS} columns; got a range map of shape {ranges.shape}"
        )
    image = np.ascontiguousarray(cameras[geometry.view_index(CAMERA_VIEW)])
    # INTER_AREA averages whole source pixels, so thin lane markings fade rather than vanish.
    small = cv2.resize(image, (CAMERA_SHAPE[1], CAMERA_SHAPE[0]), interpolation=cv2.INTER_AREA)
    camera = small.astype(np.float32).transpose(2, 0, 1) / 255.0
    crop = ranges[:, first:end]
    crop = np.where(crop == spec.no_return, spec.max_range, np.minimum(crop, spec.max_range))
    # The nearest return of each bin: a thin pole or a car's edge must not be averaged away.
    pooled = crop.reshape(LIDAR_BEAMS, LIDAR_COLUMNS, -1).min(axis=2) / spec.max_range
    return Features(
        camera=camera,
        lidar=pooled[None].astype(np.float32),
        speed=np.array([speed / SPEED_SCALE], dtype=np.float32),
    )


# -- the network --

TRUNK_FEATURES = 48  # per sensor; enough for a lane offset and a lead gap, small enough for ~300 KB of weights
HEAD_HIDDEN = 64  # the MLP that mixes the sensors' features with the speed


def _camera_trunk() -> nn.Sequential:
    """(B, 3, 32, 56) -> (B, TRUNK_FEATURES)."""
    return nn.Sequential(
        nn.Conv2d(3, 16, 5, stride=2, padding=2),  # (B, 16, 16, 28)
        nn.ReLU(),
        nn.Conv2d(16, 32, 3, stride=2, padding=1),  # (B, 32, 8, 14)
        nn.ReLU(),
        nn.Conv2d(32, 16, 3, stride=2, padding=1),  # (B, 16, 4, 7)
        nn.ReLU(),
        nn.Flatten(),  # (B, 448)
        nn.Linear(16 * 4 * 7, TRUNK_FEATURES),
        nn.ReLU(),
    )


def _lidar_trunk() -> nn.Sequential:
    """(B, 1, 32, 128) -> (B, TRUNK_FEATURES)."""
    return nn.Sequential(
        nn.Conv2d(1, 8, (3, 5), stride=2, padding=(1, 2)),  # (B, 8, 16, 64)
        nn.ReLU(),
        nn.Conv2d(8, 16, 3, stride=2, padding=1),  # (B, 16, 8, 32)
        nn.ReLU(),
        nn.Conv2d(16, 32, 3, stride=2, padding=1),  # (B, 32, 4, 16)
        nn.ReLU(),
        nn.Conv2d(32, 16, 3, stride=2, padding=1),  # (B, 16, 2, 8)
        nn.ReLU(),
        nn.Flatten(),  # (B, 256)
        nn.Linear(16 * 2 * 8, TRUNK_FEATURES),
        nn.ReLU(),
    )


class BehaviourCloningNet(nn.Module):
    """A small CNN per sensor, concatenated with the speed, then an MLP to the action.

    Inputs (any of camera / lidar the ``sensors`` set does not use is ignored):
        camera: (B, 3, 32, 56) float32 in [0, 1]
        lidar:  (B, 1, 32, 128) float32 in [0, 1]
        speed:  (B, 1) float32
    Output: (B, 2) float32 in [-1, 1], the env's [acceleration, steering] action.
    """

    def __init__(self, sensors: str) -> None:
        super().__init__()
        if sensors not in SENSOR_SETS:
            raise ValueError(f"sensors must be one of {SENSOR_SETS}, got {sensors!r}")
        self.sensors = sensors
        self.camera = _camera_trunk() if sensors in ("cameras", "both") else None
        self.lidar = _lidar_trunk() if sensors in ("lidar", "both") else None
        trunks = (self.camera is not None) + (self.lidar is not None)
        self.head = nn.Sequential(
            nn.Linear(trunks * TRUNK_FEATURES + 1, HEAD_HIDDEN),  # + 1: the speed
            nn.ReLU(),
            nn.Linear(HEAD_HIDDEN, 2),
            nn.Tanh(),
        )

    def forward(self, camera: torch.Tensor, lidar: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        parts = []
        if self.camera is not None:
            parts.append(self.camera(camera - 0.5))  # zero-centred pixels suit the default initialisation
        if self.lidar is not None:
            parts.append(self.lidar(lidar))
        return self.head(torch.cat([*parts, speed], dim=1))


# -- the members --


@dataclass(frozen=True)
class LearnedSpec:
    """How one learned member is made: its sensors, its data budget (recorded autopilot episodes,
    the first ``episodes`` of :mod:`~m4world_env.zoo.train_learned`'s fixed list, so a smaller
    budget is a subset of a larger one) and its training length (gradient steps)."""

    name: str
    sensors: str
    episodes: int
    train_steps: int
    seed: int
    version: int = 1

    def __post_init__(self) -> None:
        if self.sensors not in SENSOR_SETS:
            raise ValueError(
                f"learned member {self.name!r}: sensors must be one of {SENSOR_SETS}, got {self.sensors!r}"
            )
        if self.episodes < 1 or self.train_steps < 1:
            raise ValueError(
                f"learned member {self.name!r}: episodes and train_steps must be >= 1, "
                f"got {self.episodes} and {self.train_steps}"
            )

    @property
    def description(self) -> str:
        seen = {
            "cameras": "the FRONT camera",
            "lidar": "the forward LiDAR",
            "both": "the FRONT camera and forward LiDAR",
        }
        return (
            f"a small CNN behaviour-cloned from the IDM autopilot; sees {seen[self.sensors]} and the ego speed; "
            f"trained on {self.episodes} recorded episodes for {self.train_steps} steps"
        )


# Small budgets leave scenarios unseen (the first 8 episodes cover 8 of the 9 scenarios, once each):
# the weak end of the family. Large budgets see every scenario in every driving style.
SMALL_EPISODES = 8
LARGE_EPISODES = 48
SMALL_TRAIN_STEPS = 600
LARGE_TRAIN_STEPS = 2500
LEARNED_SPECS: tuple[LearnedSpec, ...] = (
    LearnedSpec("bc_cameras_small", "cameras", SMALL_EPISODES, SMALL_TRAIN_STEPS, seed=2101),
    LearnedSpec("bc_lidar_small", "lidar", SMALL_EPISODES, SMALL_TRAIN_STEPS, seed=2102),
    LearnedSpec("bc_both_small", "both", SMALL_EPISODES, SMALL_TRAIN_STEPS, seed=2103),
    LearnedSpec("bc_cameras_large", "cameras", LARGE_EPISODES, LARGE_TRAIN_STEPS, seed=2104),
    LearnedSpec("bc_lidar_large", "lidar", LARGE_EPISODES, LARGE_TRAIN_STEPS, seed=2105),
    LearnedSpec("bc_both_large", "both", LARGE_EPISODES, LARGE_TRAIN_STEPS, seed=2106),
)


def weights_path(spec: LearnedSpec, weights_dir: Path = WEIGHTS_DIR) -> Path:
    return Path(weights_dir) / f"{spec.name}.safetensors"


# -- loading and driving --

_CACHE: dict[tuple[str, int], tuple[BehaviourCloningNet, dict[str, str]]] = {}
_CACHE_LOCK = threading.Lock()
# torch's thread count is process-wide: drive() sets it to one for the forward pass and restores
# it, and this lock keeps two policies (or two threads) from interleaving that.
_INFERENCE_LOCK = threading.Lock()


def load_net(path: Path) -> tuple[BehaviourCloningNet, dict[str, str]]:
    """The network stored at ``path`` (eval mode, CPU) and its metadata, loaded once per file
    version (the cache key holds the file's modification time, so retrained weights are reread)."""
    path = Path(path).resolve()
    if not path.is_file():
        raise FileNotFoundError(f"no learned zoo weights at {path}: run `make zoo` to train them")
    key = (str(path), path.stat().st_mtime_ns)
    with _CACHE_LOCK:
        if key not in _CACHE:
            with safe_open(str(path), framework="pt") as f:
                meta = dict(f.metadata() or {})
            if meta.get("format") != WEIGHTS_FORMAT:
                raise ValueError(f"{path} is not a learned zoo weight file of format {WEIGHTS_FORMAT!r}: {meta}")
            net = BehaviourCloningNet(meta["sensors"])
            net.load_state_dict(load_file(str(path), device="cpu"))
            net.eval()
            for p in net.parameters():
                p.requires_grad_(False)
            _CACHE[key] = (net, meta)
        return _CACHE[key]


@contextmanager
def _one_thread() -> Iterator[None]:
    # One thread: the forward pass of a net this small gains nothing from more, and a fixed
    # count keeps its float reductions in one order whatever the process's setting.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def features_to_tensors(features: Features) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One observation's features as a batch of one: the network's (camera, lidar, speed)."""
    return (
        torch.from_numpy(features.camera)[None],
        torch.from_numpy(features.lidar)[None],
        torch.from_numpy(features.speed)[None],
    )


class LearnedPolicy(SensorPolicy):
    """Drives with a behaviour-cloned network: no memory, no randomness; the same observation and
    speed always give the same action."""

    def __init__(self, geometry: SensorGeometry, weights: Path) -> None:
        super().__init__(geometry)
        self.net, self.metadata = load_net(weights)

    def drive(self, obs: Mapping[str, np.ndarray], status: EgoStatus) -> np.ndarray:
        inputs = features_to_tensors(extract_features(obs, status.speed, self.geometry))
        with _INFERENCE_LOCK, _one_thread(), torch.no_grad():
            action = self.net(*inputs)[0]
        return action.numpy().astype(np.float32)


def learned_member(spec: LearnedSpec, weights_dir: Path = WEIGHTS_DIR) -> ZooMember:
    """The zoo member of ``spec`` whose weights are in ``weights_dir``. The file is looked for when
    the member is built, so listing the zoo works before ``make zoo``."""
    path = weights_path(spec, weights_dir)

    def build(geometry: SensorGeometry, _seed: np.random.SeedSequence) -> SensorPolicy:
        return LearnedPolicy(geometry, path)

    return ZooMember(
        name=spec.name,
        family=FAMILY,
        version=spec.version,
        seed=spec.seed,
        description=spec.description,
        builder=build,
        files=(path,),
    )


def learned_members() -> list[ZooMember]:
    """The learned family, its weights in the package's ``zoo/weights`` folder."""
    return [learned_member(spec) for spec in LEARNED_SPECS]
