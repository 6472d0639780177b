"""Sensor descriptions: the camera rig, the LiDAR and the BEV raster (paper §3.2, "Control signals").

All poses are relative to the LiDAR frame (x forward, y left, z up); see :mod:`world_model.geometry`.
These are plain, serializable dataclasses with every default visible.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from world_model.geometry import BOX_EDGES

# nuScenes ring order; the default rig uses it.
DEFAULT_CAMERA_NAMES = ("FRONT_LEFT", "FRONT", "FRONT_RIGHT", "BACK_RIGHT", "BACK", "BACK_LEFT")
# Yaw of each camera's optical axis in the LiDAR frame, degrees (counter-clockwise = to the left).
DEFAULT_CAMERA_YAWS_DEG = (55.0, 0.0, -55.0, -110.0, 180.0, 110.0)
# Horizontal fields of view, degrees: nuScenes-like, wide enough that neighbours overlap.
DEFAULT_CAMERA_HFOVS_DEG = (70.0, 70.0, 70.0, 70.0, 110.0, 70.0)

# Optical frame (x right, y down, z forward) expressed in the LiDAR frame for a camera looking
# along +x: its columns are the camera axes written in LiDAR coordinates.
_OPTICAL_TO_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class CameraSpec:
    """One pinhole camera. ``R``/``t`` map camera (OpenCV) coordinates to the LiDAR frame:
    ``p_lidar = R @ p_cam + t``."""

    name: str
    K: np.ndarray  # (3, 3) intrinsics in pixels
    R: np.ndarray  # (3, 3) camera -> LiDAR rotation
    t: np.ndarray  # (3,) camera centre in the LiDAR frame, metres
    width: int
    height: int

    def condition_matrix(self) -> np.ndarray:
        """The paper's camera condition ``[K; R; t^T]`` (7, 3), float32."""
        return np.concatenate([self.K, self.R, self.t[None, :]], axis=0).astype(np.float32)

    @property
    def hfov(self) -> float:
        """Horizontal field of view in radians."""
        return 2.0 * math.atan(0.5 * self.width / float(self.K[0, 0]))

    @property
    def yaw(self) -> float:
        """Yaw of the optical axis in the LiDAR frame, radians."""
        forward = self.R[:, 2]
        return math.atan2(forward[1], forward[0])

    def box_extent(self, corners: np.ndarray, near: float) -> tuple[int, int, int, int] | None:
        """Pixel extent ``(x0, y0, x1, y1)`` of a 3-D box given by its (8, 3) LiDAR-frame corners:
        end-exclusive (``img[y0:y1, x0:x1]``), clipped to the image; edges crossing the plane
        ``z_cam = near`` are clipped there first (a box beside the camera still has a finite
        extent). None when no part of the box is in front of the near plane or in the image.
        Occlusion is not considered."""
        pc = (corners - self.t) @ self.R  # LiDAR -> camera (R maps camera -> LiDAR)
        pts = [pc[i] for i in range(8) if pc[i, 2] >= near]
        for a, b in BOX_EDGES:
            za, zb = pc[a, 2], pc[b, 2]
            if (za >= near) != (zb >= near):
                pts.append(pc[a] + (near - za) / (zb - za) * (pc[b] - pc[a]))
        if not pts:
            return None
        q = np.array(pts)
        u = self.K[0, 0] * q[:, 0] / q[:, 2] + self.K[0, 2]
        v = self.K[1, 1] * q[:, 1] / q[:, 2] + self.K[1, 2]
        x0, x1 = max(0, math.floor(u.min())), min(self.width, math.ceil(u.max()))
        y0, y1 = max(0, math.floor(v.min())), min(self.height, math.ceil(v.max()))
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CameraSpec:
        return cls(
            name=d["name"],
            K=np.asarray(d["K"], dtype=np.float64),
            R=np.asarray(d["R"], dtype=np.float64),
            t=np.asarray(d["t"], dtype=np.float64),
            width=int(d["width"]),
            height=int(d["height"]),
        )


def make_camera(
    name: str,
    yaw_deg: float,
    hfov_deg: float,
    width: int,
    height: int,
    position: tuple[float, float, float] = (0.0, 0.0, 0.0),
    pitch_deg: float = 0.0,
) -> CameraSpec:
    """A pinhole camera looking along ``yaw_deg`` (0 = forward, +90 = left), square pixels.

    ``pitch_deg`` > 0 tilts the optical axis down. ``position`` is in the LiDAR frame.
    """
    fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
    K = np.array([[fx, 0.0, width / 2.0], [0.0, fx, height / 2.0], [0.0, 0.0, 1.0]])
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    yaw_rot = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    # Pitch down = rotation about the camera-forward frame's +y (left) axis by +pitch.
    pitch_rot = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    R = yaw_rot @ pitch_rot @ _OPTICAL_TO_FORWARD
    return CameraSpec(name=name, K=K, R=R, t=np.asarray(position, dtype=np.float64), width=width, height=height)


@dataclass(frozen=True)
class CameraRig:
    """An ordered set of cameras. The view axis of every tensor in the project follows this order."""

    cameras: tuple[CameraSpec, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    @property
    def num_views(self) -> int:
        return len(self.cameras)

    @property
    def resolution(self) -> tuple[int, int]:
        """(height, width) shared by all cameras (the rig requires one resolution)."""
        return self.cameras[0].height, self.cameras[0].width

    def condition_matrices(self) -> np.ndarray:
        """(V, 7, 3) float32 stack of ``[K; R; t^T]``."""
        return np.stack([c.condition_matrix() for c in self.cameras])

    def to_dict(self) -> dict:
        return {"cameras": [c.to_dict() for c in self.cameras]}

    @classmethod
    def from_dict(cls, d: dict) -> CameraRig:
        return cls(cameras=tuple(CameraSpec.from_dict(c) for c in d["cameras"]))


def default_rig(
    width: int = 112,
    height: int = 64,
    names: tuple[str, ...] = DEFAULT_CAMERA_NAMES,
    yaws_deg: tuple[float, ...] = DEFAULT_CAMERA_YAWS_DEG,
    hfovs_deg: tuple[float, ...] = DEFAULT_CAMERA_HFOVS_DEG,
    mount_offset: tuple[float, float, float] = (0.0, 0.0, -0.3),
    pitch_deg: float = 0.0,
) -> CameraRig:
    """The default 6-camera surround rig (nuScenes ring order), any resolution.

    Cameras sit ``mount_offset`` from the LiDAR (slightly below it, as on a roof rack). Equal
    arguments return the *same* (immutable) rig object, so identity-keyed caches downstream (the
    simulator's per-rig precomputations) are shared by every env built with the same rig.
    """
    return _default_rig(
        int(width),
        int(height),
        tuple(names),
        tuple(map(float, yaws_deg)),
        tuple(map(float, hfovs_deg)),
        tuple(map(float, mount_offset)),
        float(pitch_deg),
    )


@functools.lru_cache(maxsize=64)
def _default_rig(
    width: int,
    height: int,
    names: tuple[str, ...],
    yaws_deg: tuple[float, ...],
    hfovs_deg: tuple[float, ...],
    mount_offset: tuple[float, float, float],
    pitch_deg: float,
) -> CameraRig:
    if not (len(names) == len(yaws_deg) == len(hfovs_deg)):
        raise ValueError("names, yaws_deg and hfovs_deg must have the same length")
    if len(set(names)) != len(names):
        raise ValueError(f"camera names must be unique, got {names}")
    cams = tuple(
        make_camera(n, y, f, width, height, position=mount_offset, pitch_deg=pitch_deg)
        for n, y, f in zip(names, yaws_deg, hfovs_deg, strict=True)
    )
    for cam in cams:  # shared instance: make it immutable
        for arr in (cam.K, cam.R, cam.t):
            arr.setflags(write=False)
    return CameraRig(cameras=cams)


@dataclass(frozen=True)
class LidarSpec:
    """A spinning LiDAR producing a range map ``(beams, azimuth)`` in metres.

    Row 0 is the top beam (``elevation_max_deg``); column 0 is azimuth +180 deg and azimuth
    decreases to the right, so straight ahead (0 deg) is column ``azimuth // 2`` and the left
    side (+90 deg) is at the first quarter. Ranges are clipped to ``max_range``; a ray with no
    return within range reads ``no_return`` (0.0).
    """

    beams: int = 32
    azimuth: int = 1024
    elevation_max_deg: float = 10.0
    elevation_min_deg: float = -30.0
    max_range: float = 100.0
    no_return: float = 0.0
    mount_height: float = 1.84  # LiDAR origin above the road, metres (nuScenes-like)

    def elevations(self) -> np.ndarray:
        """(beams,) elevation of each row in radians, top first."""
        return np.deg2rad(np.linspace(self.elevation_max_deg, self.elevation_min_deg, self.beams))

    def azimuths(self) -> np.ndarray:
        """(azimuth,) azimuth of each column centre in radians, +pi first, decreasing."""
        step = 2.0 * np.pi / self.azimuth
        return np.pi - step * np.arange(self.azimuth)

    def ray_directions(self) -> np.ndarray:
        """(beams, azimuth, 3) unit ray directions in the LiDAR frame."""
        el = self.elevations()[:, None]
        az = self.azimuths()[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d: dict) -> LidarSpec:
        return cls(**d)


BEV_CLASSES = ("drivable_area", "lane_divider", "road_edge")


@dataclass(frozen=True)
class BevSpec:
    """An ego-aligned BEV raster ``{0,1}^(h, w, c)``.

    Row 0 is the far front (x = +forward_m), rows go backwards; column 0 is the far left
    (y = +half_width_m), columns go to the right: viewed as an image, forward is up and the
    ego's left is on the left. Pixel (r, c) covers the cell whose centre is
    ``x = forward_m - (r + 0.5) * m_per_px``, ``y = half_width_m - (c + 0.5) * m_per_px``.
    """

    forward_m: float = 40.0
    backward_m: float = 40.0
    half_width_m: float = 40.0
    m_per_px: float = 1.0
    classes: tuple[str, ...] = field(default=BEV_CLASSES)

    @property
    def shape(self) -> tuple[int, int, int]:
        h = round((self.forward_m + self.backward_m) / self.m_per_px)
        w = round(2 * self.half_width_m / self.m_per_px)
        return h, w, len(self.classes)

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["classes"] = list(self.classes)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> BevSpec:
        d = dict(d)
        d["classes"] = tuple(d.get("classes", BEV_CLASSES))
        return cls(**d)


# A pixel's centre in the continuous image coordinates of CameraSpec.K: pixel j spans [j, j + 1).
PIXEL_CENTRE = 0.5


def road_points(camera: CameraSpec, mount_height: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(..., 2) LiDAR-frame (x forward, y left) m of the flat road (``mount_height`` below the
    LiDAR) seen at continuous pixel coordinates ``u`` (right) and ``v`` (down), both (...);
    nan where the pixel's ray does not descend to the road (at or above the horizon)."""
    u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    rays = pixels @ np.linalg.inv(camera.K).T @ camera.R.T  # camera -> LiDAR frame directions
    drop = -mount_height - camera.t[2]  # the road relative to the camera centre (negative: below)
    down = rays[..., 2] < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(down, drop / rays[..., 2], np.nan)
    return camera.t[:2] + scale[..., None] * rays[..., :2]
