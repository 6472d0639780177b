"""Import nuScenes scenes as clips of the project's dataset format (:mod:`world_model.data.clips`).

``m4world import nuscenes --dataroot DIR --version v1.0-mini --out DATA`` reads the dataset's JSON
tables, checking every row the importer uses (:mod:`world_model.data.nuscenes_tables`), and writes
one clip per scene:

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

Every table row and every chosen scene's chains are checked before the first clip is written:
a table or scene that breaks a rule stops the import with :class:`NuScenesFormatError` and writes
nothing. A sensor file that cannot be read stops it at its scene, which gets no clip. Each clip is
written aside and renamed when complete (:func:`world_model.data.clips.write_clip`). A dataset's
preset is fixed by its first clip: importing at another one is refused before any work.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from world_model.data.clips import Clip, DatasetFormatError, list_clips, write_clip
from world_model.data.nuscenes_map import corridor_map, map_expansion, map_layers, map_route
from world_model.data.nuscenes_tables import (
    CAMERA_CHANNELS,
    LIDAR_CHANNEL,
    MICROSECONDS,
    NuScenesFormatError,
    NuScenesImportError,
    NuScenesTables,
    field_error,
    finite_number,
    read_tables,
    scene_chains,
)
from world_model.scene import CATEGORIES, Box3D, EgoState, SceneFrame, SceneObject, ScenePrompt
from world_model.sensors import DEFAULT_CAMERA_NAMES, BevSpec, CameraRig, CameraSpec, LidarSpec

if TYPE_CHECKING:
    from world_model.model.config import SensorConfig

__all__ = [
    "NuScenesFormatError",
    "NuScenesImportConfig",
    "NuScenesImportError",
    "check_dataset_preset",
    "import_nuscenes",
    "map_category",
    "open_nuscenes",
    "points_to_range_map",
]

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

# A nuScenes .pcd.bin file holds float32 x, y, z, intensity and ring index per point.
LIDAR_FLOATS_PER_POINT = 5
MAX_FPS = 100.0  # a clip's frame rate; beyond the LiDAR's 20 Hz sweeps frames only repeat them
MIN_BOX_INTERVAL_S = 1e-6  # keyframes closer than this count as this far apart for box velocities


@dataclass(frozen=True)
class NuScenesImportConfig:
    """What to import, and the model preset whose sensors (views, LiDAR, BEV) the clips match."""

    dataroot: Path
    version: str = "v1.0-mini"
    out: Path = Path("data/nuscenes")
    scenes: tuple[str, ...] = ()  # empty: every scene of the version
    preset: str = "default"
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


def _preset_sensors(preset: str) -> SensorConfig:
    from world_model.model.config import get_preset

    try:
        return get_preset(preset).sensors
    except ValueError as e:
        raise NuScenesImportError(f"--preset: {e}") from None


def _geometry(sensors: SensorConfig) -> tuple:
    """What the clips of one dataset share: the views' count and size, the range map's, the BEV's."""
    lidar = sensors.lidar
    return sensors.num_cameras, sensors.height, sensors.width, lidar.beams, lidar.azimuth, sensors.bev.shape


def _describe(geometry: tuple) -> str:
    cameras, height, width, beams, azimuth, bev = geometry
    return f"{cameras} cameras {height}x{width}, LiDAR {beams}x{azimuth}, BEV {'x'.join(map(str, bev))}"


def _clip_geometry(meta_path: Path) -> tuple:
    from world_model.model.config import SensorConfig

    try:
        static = json.loads(meta_path.read_text())["static"]
        cameras = CameraRig.from_dict(static["rig"]).cameras
        sensors = SensorConfig(
            num_cameras=len(cameras),
            height=cameras[0].height,
            width=cameras[0].width,
            lidar=LidarSpec.from_dict(static["lidar"]),
            bev=BevSpec.from_dict(static["bev"]),
        )
    except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
        raise DatasetFormatError(f"{meta_path}: not a readable clip meta.json ({e!r})") from e
    return _geometry(sensors)


def check_dataset_preset(out: Path, preset: str) -> None:
    """Refuse to import at ``preset`` into a dataset whose first clip has other sensors: a
    dataset's preset is fixed by its first clip (training reads one view, LiDAR and BEV size)."""
    from world_model.model.config import PRESETS, get_preset

    wanted = _geometry(_preset_sensors(preset))
    clips = list_clips(out) if (Path(out) / "dataset.json").exists() else []
    if not clips:
        return
    found = _clip_geometry(Path(out) / clips[0] / "meta.json")
    if found == wanted:
        return
    matches = [name for name in PRESETS if _geometry(get_preset(name).sensors) == found]
    recorded = f"preset {matches[0]!r}" if matches else "no preset's sensors"
    advice = f"import with --preset {matches[0]}" if matches else "import"
    raise NuScenesImportError(
        f"--preset {preset}: {out} holds clips at {recorded} (its first clip {clips[0]}: {_describe(found)}; "
        f"preset {preset!r}: {_describe(wanted)}); a dataset keeps its first clip's preset: {advice} "
        "into it, or give another --out"
    )


def open_nuscenes(dataroot: str | Path, version: str) -> NuScenesTables:
    """The checked tables of ``dataroot``/``version`` (:func:`read_tables`), refusing a bad path by name."""
    root = Path(dataroot)
    if not root.is_dir():
        raise NuScenesImportError(f"--dataroot {root} does not exist or is not a directory")
    if not (root / version).is_dir():
        present = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
        raise NuScenesImportError(f"--version {version!r} is not in {root} (versions there: {present or 'none'})")
    try:  # the map expansion's lane centerlines are discretized by the devkit
        import nuscenes.map_expansion.arcline_path_utils  # noqa: F401
    except ImportError as e:
        raise NuScenesImportError(
            "importing nuScenes needs nuscenes-devkit: pip install --no-deps nuscenes-devkit==1.2.0 && "
            'pip install -e ".[nuscenes]"'
        ) from e
    return read_tables(root, version)


def read_lidar_points(path: Path) -> np.ndarray:
    """(N, 3) points of a nuScenes ``.pcd.bin`` file, in its sensor frame."""
    size = path.stat().st_size
    point_bytes = LIDAR_FLOATS_PER_POINT * np.dtype(np.float32).itemsize
    if size % point_bytes:
        raise ValueError(f"{size} bytes is not a whole number of {point_bytes}-byte points")
    data = np.fromfile(path, dtype=np.float32).reshape(-1, LIDAR_FLOATS_PER_POINT)
    return data[:, :3].astype(np.float64)


class _SceneReader:
    """One scene's sensor data and annotations, from its checked chains (:func:`scene_chains`), and
    the sample_data each frame reads, whose files are checked to exist before any is read."""

    def __init__(self, tables: NuScenesTables, scene: dict, sensors: SensorConfig, fps: float) -> None:
        self.tables, self.scene, self.sensors, self.fps = tables, scene, sensors, fps
        chains = scene_chains(tables, scene)
        self.samples, self.channels, self.first = chains.samples, chains.channels, chains.first
        cs = tables.get("calibrated_sensor", self.first[LIDAR_CHANNEL]["calibrated_sensor_token"])
        self.lidar_to_ego_R = _quat_matrix(cs["rotation"])
        self.lidar_in_ego = np.asarray(cs["translation"], dtype=np.float64)
        self.lidar_spec = replace(sensors.lidar, mount_height=float(self.lidar_in_ego[2]))
        t0, t1 = self.samples[0]["timestamp"], self.samples[-1]["timestamp"]
        self.frame_times_us = [t0 + i / fps / MICROSECONDS for i in range(int((t1 - t0) * MICROSECONDS * fps) + 1)]
        self.sweeps = [self.nearest(LIDAR_CHANNEL, t) for t in self.frame_times_us]
        self.views = [[self.nearest(ch, t) for ch in CAMERA_CHANNELS] for t in self.frame_times_us]
        for sd in {sd["token"]: sd for sd in (*self.sweeps, *(sd for v in self.views for sd in v))}.values():
            if not self.path(sd).is_file():
                allowed = f"no such file in --dataroot {tables.dataroot}"
                raise field_error(tables.path("sample_data"), sd, "filename", allowed)

    def nearest(self, channel: str, t_us: float) -> dict:
        chain = self.channels[channel]
        return min(chain, key=lambda sd: abs(sd["timestamp"] - t_us))

    def path(self, sd: dict) -> Path:
        return self.tables.dataroot / sd["filename"]

    def rig(self) -> CameraRig:
        """The rig of the first keyframe's calibrated cameras, in the project's LiDAR frame."""
        cams = []
        width, height = self.sensors.width, self.sensors.height
        for name, channel in zip(DEFAULT_CAMERA_NAMES, CAMERA_CHANNELS, strict=True):
            sd = self.first[channel]
            cs = self.tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
            sx, sy = width / sd["width"], height / sd["height"]
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
            cams.append(CameraSpec(name=name, K=K, R=R, t=t, width=width, height=height))
        return CameraRig(cameras=tuple(cams))

    def ego_state(self, sd: dict) -> tuple[EgoState, float]:
        """The ego (at LIDAR_TOP's horizontal position) and the ego frame's height in the world."""
        get = self.tables.get
        pose = get("ego_pose", sd["ego_pose_token"])
        R = _quat_matrix(pose["rotation"])
        origin = np.asarray(pose["translation"], dtype=np.float64) + R @ self.lidar_in_ego
        # Speed: central difference over the neighbouring sweeps of the same channel.
        before = get("sample_data", sd["prev"]) if sd["prev"] else sd
        after = get("sample_data", sd["next"]) if sd["next"] else sd
        speed = 0.0
        if after["timestamp"] > before["timestamp"]:
            a, b = (np.asarray(get("ego_pose", x["ego_pose_token"])["translation"][:2]) for x in (before, after))
            speed = float(np.linalg.norm(b - a)) / ((after["timestamp"] - before["timestamp"]) * MICROSECONDS)
        ego = EgoState(x=float(origin[0]), y=float(origin[1]), yaw=_yaw(R), speed=speed)
        return ego, float(pose["translation"][2])

    def image(self, sd: dict) -> np.ndarray:
        from PIL import Image

        path = self.path(sd)
        try:
            with Image.open(path) as im:
                im = im.convert("RGB").resize((self.sensors.width, self.sensors.height), Image.BILINEAR)
                return np.asarray(im, dtype=np.uint8)
        except (OSError, ValueError) as e:
            raise NuScenesImportError(f"scene {self.scene['name']}: cannot read camera file {path}: {e}") from e

    def range_map(self, sd: dict) -> np.ndarray:
        path = self.path(sd)
        try:
            points = read_lidar_points(path)
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
                (times[k1] - times[k]) * MICROSECONDS, MIN_BOX_INTERVAL_S
            )
            category = self.tables.category_name(ann)
            objects.append(
                SceneObject(
                    track_id=inst,
                    category=map_category(category),
                    box=Box3D(
                        center=(float(centre[0]), float(centre[1]), float(centre[2] - ego_z)),
                        size=(float(length), float(width), float(height)),
                        yaw=float(yaw),
                    ),
                    description=category,
                    velocity=(float(velocity[0]), float(velocity[1])),
                )
            )
        return tuple(objects)

    def _annotations(self, sample: dict) -> dict[str, dict]:
        return {ann["instance_token"]: ann for ann in self.tables.annotations.get(sample["token"], [])}


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


def import_scene(reader: _SceneReader, cfg: NuScenesImportConfig) -> str:
    """Write one checked scene as a clip; returns its name."""
    from world_model.sim import ProceduralSimulator

    scene, bev_spec, dataroot = reader.scene, reader.sensors.bev, reader.tables.dataroot
    rig = reader.rig()
    prompt = ScenePrompt(text=scene.get("description", ""))
    egos = [reader.ego_state(sd) for sd in reader.sweeps]
    sim = ProceduralSimulator()
    path_xy = np.array([[e.x, e.y] for e, _ in egos])
    location = reader.tables.get("log", scene["log_token"])["location"]
    route = map_route(dataroot, location, np.array([[e.x, e.y, e.yaw] for e, _ in egos]))
    reach = math.hypot(max(bev_spec.forward_m, bev_spec.backward_m), bev_spec.half_width_m)
    # The drawn map covers the route's lanes too, so that a replay along them sees its road.
    covered = path_xy if route is None else np.concatenate([path_xy, route.centerline])
    road = map_expansion(dataroot, location, covered, margin=reach)
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
    for i, (sd, views, (ego, ego_z)) in enumerate(zip(reader.sweeps, reader.views, egos, strict=True)):
        frame = SceneFrame(
            time=i / reader.fps,
            frame_index=i,
            ego=ego,
            # Boxes at the sweep's own time, so they agree with its ego pose and points.
            objects=reader.boxes_at(sd["timestamp"], ego_z),
            map=road,
            prompt=prompt,
            rig=rig,
            lidar=reader.lidar_spec,
            bev=bev_spec,
            scenario=f"nuscenes_{scene['name']}",
        )
        frames.append(frame)
        cams.append(np.stack([reader.image(view) for view in views]))
        lidars.append(reader.range_map(sd))
        bevs.append(sim.render_bev(frame))
    name = f"nuscenes_{scene['name']}"
    meta = {"source": "nuscenes", "version": cfg.version, "scene_token": scene["token"], "bev_from": bev_from}
    write_clip(cfg.out, Clip(name, frames, np.stack(cams), np.stack(lidars), np.stack(bevs), meta=meta | route_meta))
    return name


def import_nuscenes(cfg: NuScenesImportConfig) -> list[str]:
    """Import the chosen scenes of ``cfg.version``; returns the clip names written. The preset,
    the tables, every chosen scene and their map expansions are checked before the first clip is
    written."""
    fps = finite_number(cfg.fps)
    if fps is None or not 0 < fps <= MAX_FPS:
        raise NuScenesImportError(f"fps {cfg.fps!r}: give a number of frames per second in (0, {MAX_FPS:g}]")
    sensors = _preset_sensors(cfg.preset)
    check_dataset_preset(cfg.out, cfg.preset)
    tables = open_nuscenes(cfg.dataroot, cfg.version)
    by_name = {s["name"]: s for s in tables.scenes}
    unknown = [s for s in cfg.scenes if s not in by_name]
    if unknown:
        raise NuScenesImportError(f"--scenes {unknown} not in {cfg.version} (scenes there: {sorted(by_name)})")
    chosen = [by_name[s] for s in cfg.scenes] if cfg.scenes else list(tables.scenes)
    if not chosen:
        raise NuScenesImportError(f"{tables.path('scene')} lists no scenes: there is nothing to import")
    readers = [_SceneReader(tables, scene, sensors, cfg.fps) for scene in chosen]
    for location in sorted({tables.get("log", scene["log_token"])["location"] for scene in chosen}):
        map_layers(tables.dataroot, location)  # its map expansion, where present, is checked as it is read
    return [import_scene(reader, cfg) for reader in readers]
