"""Import nuScenes scenes as clips of the project's dataset format (:mod:`world_model.data.clips`).

``m4world import nuscenes --dataroot DIR --version v1.0-mini --out DATA`` reads the dataset
through the official ``nuscenes-devkit`` (extra ``[nuscenes]``) and writes one clip per scene:

* frames at ``fps`` (10 Hz by default) between the scene's first and last keyframe; each frame
  takes the LIDAR_TOP sample_data (keyframe or 20 Hz sweep) nearest in time, its ego pose, and
  each camera's sample_data nearest in time (cameras run at 12 Hz);
* boxes: annotations exist at the 2 Hz keyframes only; a frame gets each instance's box
  interpolated to its LiDAR sweep's time, linearly (centre) and along the shortest arc (yaw);
* cameras: the six images resized to the preset's resolution, intrinsics scaled accordingly,
  extrinsics from ``calibrated_sensor`` expressed in the project's LiDAR frame;
* LiDAR: the sweep's points binned into the preset's range map (nearest return per cell);
* BEV: from the map expansion (``maps/expansion/<location>.json``: drivable area, lane and road
  dividers) where it is present, else a drivable corridor along the logged ego path;
* route: where the map expansion is present and every logged pose is on one of its lanes, the
  driven lanes' joined centerline (``meta.json``: ``route_centerline``, ``route_lanes``,
  ``route_lane_width``; :func:`world_model.data.nuscenes_map.map_route`), which log replay drives on.

Frames: the nuScenes global frame (x east, y north, z up) is used as the world frame. The project's
LiDAR frame sits at LIDAR_TOP's position, yawed with the ego (x forward, y left, z up); nuScenes'
LIDAR_TOP sensor frame (x right, y forward, z up) reaches it through its ``calibrated_sensor``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from world_model.data.clips import write_clip
from world_model.data.nuscenes_map import corridor_map, map_expansion, map_route
from world_model.scene import CATEGORIES, Box3D, EgoState, SceneFrame, SceneObject, ScenePrompt
from world_model.sensors import DEFAULT_CAMERA_NAMES, BevSpec, CameraRig, CameraSpec, LidarSpec

if TYPE_CHECKING:
    from nuscenes.nuscenes import NuScenes

# nuScenes category prefix -> the project's category; the longest matching prefix wins.
CATEGORY_MAP: dict[str, str] = {
    "vehicle.car": "car",
    "vehicle.emergency": "car",
    "vehicle.truck": "truck",
    "vehicle.construction": "truck",
    "vehicle.trailer": "truck",
    "vehicle.bus": "bus",
    "vehicle.motorcycle": "motorcycle",
    "vehicle.bicycle": "cyclist",
    "human.pedestrian": "pedestrian",
    "movable_object.trafficcone": "cone",
    "movable_object.barrier": "barrier",
}
# Categories with no counterpart (animals, debris, push-carts, bicycle racks) are kept as a
# static obstacle of this category, with their logged size.
FALLBACK_CATEGORY = "barrier"

MICROSECONDS = 1e-6


class NuScenesImportError(ValueError):
    """A nuScenes dataroot, version, scene or sample file that cannot be imported."""


@dataclass(frozen=True)
class NuScenesImportConfig:
    """What to import and at which sensor resolution (the preset's)."""

    dataroot: Path
    version: str = "v1.0-mini"
    out: Path = Path("data/nuscenes")
    scenes: tuple[str, ...] = ()  # empty: every scene of the version
    height: int = 64
    width: int = 112
    lidar: LidarSpec = field(default_factory=LidarSpec)
    bev: BevSpec = field(default_factory=BevSpec)
    fps: float = 10.0


def map_category(nuscenes_category: str) -> str:
    """The project's category for a nuScenes category name (``FALLBACK_CATEGORY`` if none)."""
    best = max((p for p in CATEGORY_MAP if nuscenes_category.startswith(p)), key=len, default=None)
    category = CATEGORY_MAP[best] if best else FALLBACK_CATEGORY
    assert category in CATEGORIES
    return category


def _quat_matrix(q: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation of a nuScenes (w, x, y, z) quaternion."""
    from pyquaternion import Quaternion

    return Quaternion(q).rotation_matrix


def _yaw(rotation: np.ndarray) -> float:
    return math.atan2(rotation[1, 0], rotation[0, 0])


def open_nuscenes(dataroot: str | Path, version: str) -> NuScenes:
    """The devkit's ``NuScenes`` for ``dataroot``/``version``, refusing a bad path by name."""
    root = Path(dataroot)
    if not root.is_dir():
        raise NuScenesImportError(f"--dataroot {root} does not exist or is not a directory")
    if not (root / version).is_dir():
        present = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
        raise NuScenesImportError(f"--version {version!r} is not in {root} (versions there: {present or 'none'})")
    try:
        from nuscenes.nuscenes import NuScenes
    except ImportError as e:
        raise NuScenesImportError(
            "importing nuScenes needs nuscenes-devkit: pip install --no-deps nuscenes-devkit==1.2.0 && "
            'pip install -e ".[nuscenes]"'
        ) from e
    try:
        return NuScenes(version=version, dataroot=str(root), verbose=False)
    except (FileNotFoundError, AssertionError, KeyError, ValueError) as e:  # ValueError: bad JSON
        raise NuScenesImportError(f"{root / version}: not a readable nuScenes table set ({e})") from e


class _SceneReader:
    """Reads one scene's sensor data and annotations through the devkit."""

    def __init__(self, nusc: NuScenes, scene: dict, cfg: NuScenesImportConfig) -> None:
        self.nusc, self.scene, self.cfg = nusc, scene, cfg
        first = nusc.get("sample", scene["first_sample_token"])
        self.samples = [first]
        while self.samples[-1]["next"]:
            self.samples.append(nusc.get("sample", self.samples[-1]["next"]))
        if "LIDAR_TOP" not in first["data"]:
            raise NuScenesImportError(f"scene {scene['name']}: no LIDAR_TOP sample_data")
        lidar_sd = nusc.get("sample_data", first["data"]["LIDAR_TOP"])
        cs = nusc.get("calibrated_sensor", lidar_sd["calibrated_sensor_token"])
        self.lidar_to_ego_R = _quat_matrix(cs["rotation"])
        self.lidar_in_ego = np.asarray(cs["translation"], dtype=np.float64)
        self.lidar_spec = replace(cfg.lidar, mount_height=float(self.lidar_in_ego[2]))
        used = ("LIDAR_TOP", *(f"CAM_{n}" for n in DEFAULT_CAMERA_NAMES))
        self.channels = {ch: self._chain(first["data"][ch]) for ch in used if ch in first["data"]}

    def _chain(self, token: str) -> list[dict]:
        """Every sample_data (keyframes and sweeps) of one channel over the scene, in time order."""
        sd = self.nusc.get("sample_data", token)
        while sd["prev"]:
            sd = self.nusc.get("sample_data", sd["prev"])
        out = [sd]
        while out[-1]["next"]:
            out.append(self.nusc.get("sample_data", out[-1]["next"]))
        return out

    def nearest(self, channel: str, t_us: float) -> dict:
        chain = self.channels[channel]
        return min(chain, key=lambda sd: abs(sd["timestamp"] - t_us))

    def path(self, sd: dict) -> Path:
        return Path(self.nusc.dataroot) / sd["filename"]

    def rig(self) -> CameraRig:
        """The rig of the first keyframe's calibrated cameras, in the project's LiDAR frame."""
        first = self.samples[0]
        cams = []
        for name in DEFAULT_CAMERA_NAMES:
            channel = f"CAM_{name}"
            if channel not in first["data"]:
                raise NuScenesImportError(f"scene {self.scene['name']}: no {channel} sample_data")
            sd = self.nusc.get("sample_data", first["data"][channel])
            cs = self.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            sx, sy = self.cfg.width / sd["width"], self.cfg.height / sd["height"]
            K0 = np.asarray(cs["camera_intrinsic"], dtype=np.float64)
            # Resize maps pixel centres: u' + 0.5 = (u + 0.5) * s.
            K = np.array(
                [
                    [K0[0, 0] * sx, 0.0, (K0[0, 2] + 0.5) * sx - 0.5],
                    [0.0, K0[1, 1] * sy, (K0[1, 2] + 0.5) * sy - 0.5],
                    [0.0, 0.0, 1.0],
                ]
            )
            # nuScenes camera axes are OpenCV's; the ego frame's axes are the LiDAR frame's.
            R = _quat_matrix(cs["rotation"])
            t = np.asarray(cs["translation"], dtype=np.float64) - self.lidar_in_ego
            cams.append(CameraSpec(name=name, K=K, R=R, t=t, width=self.cfg.width, height=self.cfg.height))
        return CameraRig(cameras=tuple(cams))

    def ego_state(self, sd: dict) -> tuple[EgoState, float]:
        """The ego (at LIDAR_TOP's horizontal position) and the ego frame's height in the world."""
        pose = self.nusc.get("ego_pose", sd["ego_pose_token"])
        R = _quat_matrix(pose["rotation"])
        origin = np.asarray(pose["translation"], dtype=np.float64) + R @ self.lidar_in_ego
        # Speed: central difference over the neighbouring sweeps of the same channel.
        before = self.nusc.get("sample_data", sd["prev"]) if sd["prev"] else sd
        after = self.nusc.get("sample_data", sd["next"]) if sd["next"] else sd
        speed = 0.0
        if after["timestamp"] > before["timestamp"]:
            a, b = (
                np.asarray(self.nusc.get("ego_pose", x["ego_pose_token"])["translation"][:2]) for x in (before, after)
            )
            speed = float(np.linalg.norm(b - a)) / ((after["timestamp"] - before["timestamp"]) * MICROSECONDS)
        ego = EgoState(x=float(origin[0]), y=float(origin[1]), yaw=_yaw(R), speed=speed)
        return ego, float(pose["translation"][2])

    def image(self, sd: dict) -> np.ndarray:
        from PIL import Image

        path = self.path(sd)
        try:
            with Image.open(path) as im:
                im = im.convert("RGB").resize((self.cfg.width, self.cfg.height), Image.BILINEAR)
                return np.asarray(im, dtype=np.uint8)
        except (OSError, ValueError) as e:
            raise NuScenesImportError(f"scene {self.scene['name']}: cannot read camera file {path}: {e}") from e

    def range_map(self, sd: dict) -> np.ndarray:
        from nuscenes.utils.data_classes import LidarPointCloud

        path = self.path(sd)
        try:
            points = LidarPointCloud.from_file(str(path)).points[:3].T.astype(np.float64)
        except (OSError, ValueError) as e:
            raise NuScenesImportError(f"scene {self.scene['name']}: cannot read LiDAR file {path}: {e}") from e
        # Sensor frame -> ego frame, then to the project's LiDAR frame (same axes, origin at the sensor).
        in_ego = points @ self.lidar_to_ego_R.T + self.lidar_in_ego
        return points_to_range_map(in_ego - self.lidar_in_ego, self.lidar_spec)

    def boxes_at(self, t_us: float, ego_z: float) -> tuple[SceneObject, ...]:
        """Every instance annotated at the keyframes around ``t_us``, interpolated to ``t_us``."""
        times = [s["timestamp"] for s in self.samples]
        k = int(np.clip(np.searchsorted(times, t_us, side="right") - 1, 0, len(times) - 1))
        k1 = min(k + 1, len(times) - 1)
        a = self._annotations(self.samples[k])
        b = self._annotations(self.samples[k1])
        w = 0.0 if k1 == k else float(np.clip((t_us - times[k]) / (times[k1] - times[k]), 0.0, 1.0))
        objects = []
        for inst, ann in a.items():
            other = b.get(inst, ann)
            centre = (1 - w) * np.asarray(ann["translation"]) + w * np.asarray(other["translation"])
            ya, yb = _yaw(_quat_matrix(ann["rotation"])), _yaw(_quat_matrix(other["rotation"]))
            yaw = ya + w * math.remainder(yb - ya, 2 * math.pi)
            width, length, height = ann["size"]  # nuScenes sizes are (w, l, h)
            velocity = (np.asarray(other["translation"][:2]) - np.asarray(ann["translation"][:2])) / max(
                (times[k1] - times[k]) * MICROSECONDS, 1e-6
            )
            objects.append(
                SceneObject(
                    track_id=inst,
                    category=map_category(ann["category_name"]),
                    box=Box3D(
                        center=(float(centre[0]), float(centre[1]), float(centre[2] - ego_z)),
                        size=(float(length), float(width), float(height)),
                        yaw=float(yaw),
                    ),
                    description=ann["category_name"],
                    velocity=(float(velocity[0]), float(velocity[1])),
                )
            )
        return tuple(objects)

    def _annotations(self, sample: dict) -> dict[str, dict]:
        out = {}
        for token in sample["anns"]:
            ann = self.nusc.get("sample_annotation", token)
            inst = self.nusc.get("instance", ann["instance_token"])
            out[ann["instance_token"]] = {
                **ann,
                "category_name": self.nusc.get("category", inst["category_token"])["name"],
            }
        return out


def points_to_range_map(points: np.ndarray, spec: LidarSpec) -> np.ndarray:
    """(N, 3) LiDAR-frame points -> (beams, azimuth) float32 range map, nearest return per cell.

    A point lands in the row of the nearest beam elevation and the column whose azimuth centre is
    nearest (:meth:`LidarSpec.azimuths`); points outside the elevation span by more than half a
    beam spacing, or beyond ``max_range``, are dropped."""
    out = np.full((spec.beams, spec.azimuth), np.inf, dtype=np.float64)
    r = np.linalg.norm(points, axis=1)
    keep = (r > 0) & (r <= spec.max_range)
    p, r = points[keep], r[keep]
    elevation = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    spacing = (spec.elevation_max_deg - spec.elevation_min_deg) / max(spec.beams - 1, 1)
    row = np.rint((spec.elevation_max_deg - elevation) / spacing).astype(np.int64)
    col = np.rint((math.pi - np.arctan2(p[:, 1], p[:, 0])) / (2 * math.pi / spec.azimuth)).astype(np.int64)
    col %= spec.azimuth
    inside = (row >= 0) & (row < spec.beams)
    np.minimum.at(out, (row[inside], col[inside]), r[inside])
    out[np.isinf(out)] = spec.no_return
    return out.astype(np.float32)


def import_scene(nusc: NuScenes, scene: dict, cfg: NuScenesImportConfig) -> str:
    """Write one scene as a clip; returns its name."""
    from world_model.sim import ProceduralSimulator

    reader = _SceneReader(nusc, scene, cfg)
    t0, t1 = reader.samples[0]["timestamp"], reader.samples[-1]["timestamp"]
    count = int((t1 - t0) * MICROSECONDS * cfg.fps) + 1
    rig = reader.rig()
    prompt = ScenePrompt(text=scene.get("description", ""))
    sweeps = [reader.nearest("LIDAR_TOP", t0 + i / cfg.fps / MICROSECONDS) for i in range(count)]
    egos = [reader.ego_state(sd) for sd in sweeps]
    sim = ProceduralSimulator()
    path_xy = np.array([[e.x, e.y] for e, _ in egos])
    location = nusc.get("log", scene["log_token"])["location"]
    route = map_route(nusc.dataroot, location, np.array([[e.x, e.y, e.yaw] for e, _ in egos]))
    reach = math.hypot(max(cfg.bev.forward_m, cfg.bev.backward_m), cfg.bev.half_width_m)
    # The drawn map covers the route's lanes too, so that a replay along them sees its road.
    covered = path_xy if route is None else np.concatenate([path_xy, route.centerline])
    road = map_expansion(nusc.dataroot, location, covered, margin=reach)
    bev_from = "map_expansion" if road is not None else "ego_path"
    road = road or corridor_map(path_xy)
    route_meta = (
        {
            "route_lanes": list(route.lanes),
            "route_centerline": np.round(route.centerline, 3).tolist(),
            "route_lane_width": round(route.lane_width, 3),
        }
        if route is not None
        else {}
    )
    frames, cams, lidars, bevs = [], [], [], []
    for i, (sd, (ego, ego_z)) in enumerate(zip(sweeps, egos, strict=True)):
        t_us = t0 + i / cfg.fps / MICROSECONDS
        frame = SceneFrame(
            time=i / cfg.fps,
            frame_index=i,
            ego=ego,
            # Boxes at the sweep's own time, so they agree with its ego pose and points.
            objects=reader.boxes_at(sd["timestamp"], ego_z),
            map=road,
            prompt=prompt,
            rig=rig,
            lidar=reader.lidar_spec,
            bev=cfg.bev,
            scenario=f"nuscenes_{scene['name']}",
        )
        frames.append(frame)
        cams.append(np.stack([reader.image(reader.nearest(f"CAM_{n}", t_us)) for n in DEFAULT_CAMERA_NAMES]))
        lidars.append(reader.range_map(sd))
        bevs.append(sim.render_bev(frame))
    name = f"nuscenes_{scene['name']}"
    write_clip(
        cfg.out,
        name,
        frames,
        np.stack(cams),
        np.stack(lidars),
        np.stack(bevs),
        extra_meta={
            "source": "nuscenes",
            "version": cfg.version,
            "scene_token": scene["token"],
            "bev_from": bev_from,
            **route_meta,
        },
    )
    return name


def import_nuscenes(cfg: NuScenesImportConfig) -> list[str]:
    """Import the chosen scenes of ``cfg.version``; returns the clip names written."""
    nusc = open_nuscenes(cfg.dataroot, cfg.version)
    by_name = {s["name"]: s for s in nusc.scene}
    unknown = [s for s in cfg.scenes if s not in by_name]
    if unknown:
        raise NuScenesImportError(f"--scenes {unknown} not in {cfg.version} (scenes there: {sorted(by_name)})")
    chosen = [by_name[s] for s in cfg.scenes] if cfg.scenes else list(nusc.scene)
    return [import_scene(nusc, scene, cfg) for scene in chosen]
