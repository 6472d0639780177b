"""A miniature nuScenes dataset in the devkit's own JSON schema, written in a fraction of a second.

Two scenes of three 2 Hz keyframes with one LiDAR sweep between keyframes; six cameras and
LIDAR_TOP calibrated like the real rig (LIDAR_TOP x right, y forward; cameras with OpenCV axes);
one car annotated at a known pose and one LiDAR return at a known place, so tests can check where
they land after the import. scene-0002's location has a map expansion with lanes; its ego turns left
along one of them. Images are small (``IMAGE_W`` x ``IMAGE_H``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image
from pyquaternion import Quaternion

VERSION = "v1.0-mini"
IMAGE_W, IMAGE_H = 160, 90
FX = 126.0  # pixels; the real rig's ~1266 at 1600 px, scaled
LIDAR_IN_EGO = (0.94, 0.0, 1.84)
# LIDAR_TOP sensor -> ego: a -90 deg yaw (sensor x right, y forward).
LIDAR_ROTATION = Quaternion(axis=(0, 0, 1), angle=-math.pi / 2)
CAMERA_YAWS_DEG = {
    "CAM_FRONT": 0.0,
    "CAM_FRONT_LEFT": 55.0,
    "CAM_FRONT_RIGHT": -55.0,
    "CAM_BACK": 180.0,
    "CAM_BACK_LEFT": 110.0,
    "CAM_BACK_RIGHT": -110.0,
}
CAMERA_IN_EGO = (1.7, 0.0, 1.5)
# OpenCV camera axes (x right, y down, z forward) written in the ego frame, for a forward camera.
OPENCV_TO_EGO = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
EGO_START = (100.0, 200.0)
EGO_YAW = math.pi / 2  # driving north (+y)
EGO_SPEED = 5.0  # m/s
EGO_Z = 0.3  # the ego frame's height in the global frame
# The annotated car, in the ego frame of the first keyframe: 20 m ahead, 2 m left, centre 0.8 m up.
CAR_IN_EGO = (20.0, 2.0, 0.8)
CAR_SIZE_WLH = (1.9, 4.5, 1.6)
# The LiDAR return: straight left of the sensor, 12 m away, on beam row 5 of the default LidarSpec.
POINT_RANGE = 12.0
POINT_ROW = 5
KEYFRAMES = 3
SCENES = ("scene-0001", "scene-0002")
# scene-0002's location has a map expansion; scene-0001's has none (its BEV comes from the ego path).
LOCATIONS = ("mini-nomap", "mini-town")
# The map expansion: a drivable rectangle around the ego's road, a lane divider 2 m left of the
# LiDAR's path (the ego drives north along x = EGO_START[0]), a road divider 6 m right of it.
DRIVABLE_X, DRIVABLE_Y = (90.0, 110.0), (150.0, 400.0)
LANE_DIVIDER_X = EGO_START[0] - 2.0
ROAD_DIVIDER_X = EGO_START[0] + 6.0
# Its lanes (arcline paths): north along x = EGO_START[0] up to the ego's start, a connector turning
# left (west) on a quarter circle, a lane west; and an oncoming lane that the route must not take.
TURN_RADIUS = 10.0
TURN_CENTRE = (EGO_START[0] - TURN_RADIUS, EGO_START[1])
LANE_IN_START_Y = 140.0
LANE_OUT_END_X = 30.0
LANE_WIDTH = 3.6  # lane_in's polygon
WEST_ARM_Y = (TURN_CENTRE[1] + TURN_RADIUS - 5.0, TURN_CENTRE[1] + TURN_RADIUS + 5.0)  # drivable, x < 90
ONCOMING_X = EGO_START[0] + 4.0


def token(*parts: object) -> str:
    return "t" + "_".join(str(p) for p in parts)


def camera_rotation(yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ OPENCV_TO_EGO


def intrinsics() -> np.ndarray:
    return np.array([[FX, 0.0, IMAGE_W / 2], [0.0, FX, IMAGE_H / 2], [0.0, 0.0, 1.0]])


def car_pixel_original() -> tuple[float, float]:
    """Where the car's centre lands in CAM_FRONT's original image at the first keyframe."""
    p_cam = OPENCV_TO_EGO.T @ (np.array(CAR_IN_EGO) - np.array(CAMERA_IN_EGO))
    uvw = intrinsics() @ p_cam
    return float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2])


def point_elevation_rad() -> float:
    return math.radians(np.linspace(10.0, -30.0, 32)[POINT_ROW])


def ego_pose(t: float, scene: int = 0) -> tuple[list[float], list[float]]:
    """scene-0001's ego drives straight north; scene-0002's turns left along the map's connector
    (a circle of ``TURN_RADIUS`` about ``TURN_CENTRE``), at ``EGO_SPEED`` both."""
    if scene == 0:
        x = EGO_START[0] + EGO_SPEED * t * math.cos(EGO_YAW)
        y = EGO_START[1] + EGO_SPEED * t * math.sin(EGO_YAW)
        yaw = EGO_YAW
    else:
        turned = EGO_SPEED * t / TURN_RADIUS
        x = TURN_CENTRE[0] + TURN_RADIUS * math.cos(turned)
        y = TURN_CENTRE[1] + TURN_RADIUS * math.sin(turned)
        yaw = EGO_YAW + turned
    return [x, y, EGO_Z], list(Quaternion(axis=(0, 0, 1), angle=yaw).elements)


def ego_to_global(p: np.ndarray, t: float, scene: int = 0) -> np.ndarray:
    trans, rot = ego_pose(t, scene)
    return Quaternion(rot).rotation_matrix @ p + np.array(trans)


def write_mini_nuscenes(root: Path) -> Path:
    """Write the miniature dataset under ``root``; returns ``root``."""
    tables: dict[str, list[dict]] = {
        k: []
        for k in (
            "attribute",
            "calibrated_sensor",
            "category",
            "ego_pose",
            "instance",
            "log",
            "map",
            "sample",
            "sample_annotation",
            "sample_data",
            "scene",
            "sensor",
            "visibility",
        )
    }
    tables["category"] = [
        {"token": "cat_car", "name": "vehicle.car", "description": ""},
        {"token": "cat_animal", "name": "animal", "description": ""},
    ]
    tables["visibility"] = [{"token": "4", "level": "v80-100", "description": ""}]
    channels = ["LIDAR_TOP", *CAMERA_YAWS_DEG]
    for ch in channels:
        modality = "lidar" if ch == "LIDAR_TOP" else "camera"
        tables["sensor"].append({"token": token("sensor", ch), "channel": ch, "modality": modality})
        if ch == "LIDAR_TOP":
            cs = {"translation": list(LIDAR_IN_EGO), "rotation": list(LIDAR_ROTATION.elements), "camera_intrinsic": []}
        else:
            rot = Quaternion(matrix=camera_rotation(CAMERA_YAWS_DEG[ch]))
            cs = {
                "translation": list(CAMERA_IN_EGO),
                "rotation": list(rot.elements),
                "camera_intrinsic": intrinsics().tolist(),
            }
        tables["calibrated_sensor"].append({"token": token("cs", ch), "sensor_token": token("sensor", ch), **cs})
    tables["map"] = [{"token": "map0", "filename": "maps/mini.png", "category": "semantic_prior", "log_tokens": []}]
    (root / "maps").mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(root / "maps" / "mini.png")
    rng = np.random.default_rng(0)
    for si, scene in enumerate(SCENES):
        log = token("log", si)
        tables["log"].append(
            {
                "token": log,
                "logfile": scene,
                "vehicle": "n015",
                "date_captured": "2018-07-24",
                "location": LOCATIONS[si],
            }
        )
        tables["map"][0]["log_tokens"].append(log)
        t0_us = 1_532_402_927_000_000 + si * 100_000_000
        samples = [token("sample", si, k) for k in range(KEYFRAMES)]
        for k, s in enumerate(samples):
            tables["sample"].append(
                {
                    "token": s,
                    "timestamp": t0_us + k * 500_000,
                    "prev": samples[k - 1] if k else "",
                    "next": samples[k + 1] if k + 1 < KEYFRAMES else "",
                    "scene_token": token("scene", si),
                }
            )
        tables["scene"].append(
            {
                "token": token("scene", si),
                "log_token": log,
                "nbr_samples": KEYFRAMES,
                "first_sample_token": samples[0],
                "last_sample_token": samples[-1],
                "name": scene,
                "description": "Night, rain, turn right at intersection" if si else "Wait at light, peds crossing",
            }
        )
        for inst, cat, offset in (("car", "cat_car", CAR_IN_EGO), ("dog", "cat_animal", (-6.0, -4.0, 0.3))):
            anns = [token("ann", si, inst, k) for k in range(KEYFRAMES)]
            tables["instance"].append(
                {
                    "token": token("inst", si, inst),
                    "category_token": cat,
                    "nbr_annotations": KEYFRAMES,
                    "first_annotation_token": anns[0],
                    "last_annotation_token": anns[-1],
                }
            )
            for k, a in enumerate(anns):
                t = 0.5 * k
                # The car keeps pace with the ego (its ego-frame pose stays put); the dog stands still.
                centre = ego_to_global(np.array(offset), t if inst == "car" else 0.0, si)
                tables["sample_annotation"].append(
                    {
                        "token": a,
                        "sample_token": samples[k],
                        "instance_token": token("inst", si, inst),
                        "attribute_tokens": [],
                        "visibility_token": "4",
                        "translation": centre.tolist(),
                        "size": list(CAR_SIZE_WLH if inst == "car" else (0.4, 0.9, 0.6)),
                        "rotation": ego_pose(t if inst == "car" else 0.0, si)[1],
                        "prev": anns[k - 1] if k else "",
                        "next": anns[k + 1] if k + 1 < KEYFRAMES else "",
                        "num_lidar_pts": 1,
                        "num_radar_pts": 0,
                    }
                )
        for ch in channels:
            # LiDAR: keyframes plus one sweep between each pair (20 Hz would be 9; one shows the mechanism).
            times = [0.5 * k for k in range(KEYFRAMES)]
            if ch == "LIDAR_TOP":
                times = sorted(times + [0.5 * k + 0.25 for k in range(KEYFRAMES - 1)])
            sds = [token("sd", si, ch, i) for i in range(len(times))]
            for i, (sd, t) in enumerate(zip(sds, times, strict=True)):
                key = float(t * 2).is_integer()
                folder = "samples" if key else "sweeps"
                ext = "pcd.bin" if ch == "LIDAR_TOP" else "jpg"
                filename = f"{folder}/{ch}/{scene}__{ch}__{i}.{ext}"
                path = root / filename
                path.parent.mkdir(parents=True, exist_ok=True)
                if ch == "LIDAR_TOP":
                    _write_lidar(path, rng)
                else:
                    _write_image(path, bright=(ch == "CAM_FRONT"))
                trans, rot = ego_pose(t, si)
                ego_token = token("ego", si, ch, i)
                tables["ego_pose"].append(
                    {"token": ego_token, "timestamp": t0_us + int(t * 1e6), "translation": trans, "rotation": rot}
                )
                tables["sample_data"].append(
                    {
                        "token": sd,
                        "sample_token": samples[min(int(t * 2), KEYFRAMES - 1)],
                        "ego_pose_token": ego_token,
                        "calibrated_sensor_token": token("cs", ch),
                        "timestamp": t0_us + int(t * 1e6),
                        "fileformat": "pcd" if ch == "LIDAR_TOP" else "jpg",
                        "is_key_frame": key,
                        "height": 0 if ch == "LIDAR_TOP" else IMAGE_H,
                        "width": 0 if ch == "LIDAR_TOP" else IMAGE_W,
                        "filename": filename,
                        "prev": sds[i - 1] if i else "",
                        "next": sds[i + 1] if i + 1 < len(sds) else "",
                    }
                )
    _write_map_expansion(map_file(root))
    (root / VERSION).mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (root / VERSION / f"{name}.json").write_text(json.dumps(rows))
    return root


def _write_image(path: Path, bright: bool) -> None:
    """A dark image; CAM_FRONT's carries a white square centred where the car projects."""
    img = np.full((IMAGE_H, IMAGE_W, 3), 20, np.uint8)
    if bright:
        u, v = car_pixel_original()
        img[int(v) - 6 : int(v) + 7, int(u) - 6 : int(u) + 7] = 255
    Image.fromarray(img).save(path, quality=95)


def _write_lidar(path: Path, rng: np.random.Generator) -> None:
    """Points in the LIDAR_TOP sensor frame (x right, y forward), 5 float32 per point: the known
    return straight left at ``POINT_RANGE`` on row ``POINT_ROW``, plus far ones on the right."""
    el = point_elevation_rad()
    left = np.array([0.0, POINT_RANGE * math.cos(el), POINT_RANGE * math.sin(el)])  # project frame
    sensor = LIDAR_ROTATION.rotation_matrix.T @ left
    far = np.stack([rng.uniform(30, 60, 16), rng.uniform(-5, 5, 16), rng.uniform(-1, 0, 16)], axis=1)
    pts = np.concatenate([sensor[None], far])
    data = np.concatenate([pts, np.zeros((len(pts), 2))], axis=1).astype(np.float32)
    data.tofile(path)


def turn_point(angle: float) -> tuple[float, float]:
    """The connector's centerline point ``angle`` radians into the left turn."""
    return TURN_CENTRE[0] + TURN_RADIUS * math.cos(angle), TURN_CENTRE[1] + TURN_RADIUS * math.sin(angle)


def _straight(x: float, y: float, yaw: float, length: float) -> dict:
    end = (x + length * math.cos(yaw), y + length * math.sin(yaw), yaw)
    return {
        "start_pose": [x, y, yaw],
        "end_pose": list(end),
        "shape": "LSL",
        "radius": 999.0,
        "segment_length": [0.0, length, 0.0],
    }


def _rectangle(prefix: str, x: tuple[float, float], y: tuple[float, float]) -> tuple[list[dict], list[str]]:
    corners = [(x[0], y[0]), (x[1], y[0]), (x[1], y[1]), (x[0], y[1])]
    return [{"token": f"{prefix}{i}", "x": a, "y": b} for i, (a, b) in enumerate(corners)], [
        f"{prefix}{i}" for i in range(4)
    ]


def _write_map_expansion(path: Path) -> None:
    """The map expansion's layers that the importer reads (node, line, polygon, drivable_area,
    lane_divider, road_divider, lane, lane_connector, arcline_path_3, connectivity)."""
    x0, (y0, y1) = DRIVABLE_X[0], DRIVABLE_Y
    nodes, road_ring = _rectangle("n", DRIVABLE_X, DRIVABLE_Y)
    west, west_ring = _rectangle("w", (LANE_OUT_END_X - 10.0, x0), WEST_ARM_Y)
    half = LANE_WIDTH / 2
    lane_in, lane_in_ring = _rectangle(
        "li", (EGO_START[0] - half, EGO_START[0] + half), (LANE_IN_START_Y, EGO_START[1])
    )
    nodes += west + lane_in
    nodes += [
        {"token": "ld0", "x": LANE_DIVIDER_X, "y": y0},
        {"token": "ld1", "x": LANE_DIVIDER_X, "y": y1},
        {"token": "rd0", "x": ROAD_DIVIDER_X, "y": y0},
        {"token": "rd1", "x": ROAD_DIVIDER_X, "y": y1},
    ]
    turn_end = turn_point(math.pi / 2)
    layers = {
        "version": "1.3",
        "node": nodes,
        "polygon": [
            {"token": "p0", "exterior_node_tokens": road_ring, "holes": []},
            {"token": "p1", "exterior_node_tokens": west_ring, "holes": []},
            {"token": "p_lane_in", "exterior_node_tokens": lane_in_ring, "holes": []},
        ],
        "line": [{"token": "l0", "node_tokens": ["ld0", "ld1"]}, {"token": "l1", "node_tokens": ["rd0", "rd1"]}],
        "drivable_area": [{"token": "da0", "polygon_tokens": ["p0", "p1"]}],
        "lane_divider": [{"token": "d0", "line_token": "l0", "lane_divider_segments": []}],
        "road_divider": [{"token": "d1", "line_token": "l1", "road_segment_token": ""}],
        "lane": [
            {"token": "lane_in", "polygon_token": "p_lane_in", "lane_type": "CAR"},
            {"token": "lane_out", "polygon_token": "", "lane_type": "CAR"},
            {"token": "lane_oncoming", "polygon_token": "", "lane_type": "CAR"},
        ],
        "lane_connector": [{"token": "turn_left", "polygon_token": ""}],
        "arcline_path_3": {
            "lane_in": [_straight(EGO_START[0], LANE_IN_START_Y, EGO_YAW, EGO_START[1] - LANE_IN_START_Y)],
            "turn_left": [
                {
                    "start_pose": [EGO_START[0], EGO_START[1], EGO_YAW],
                    "end_pose": [*turn_end, math.pi],
                    "shape": "LSL",
                    "radius": TURN_RADIUS,
                    "segment_length": [TURN_RADIUS * math.pi / 2, 0.0, 0.0],
                }
            ],
            "lane_out": [_straight(*turn_end, math.pi, turn_end[0] - LANE_OUT_END_X)],
            "lane_oncoming": [_straight(ONCOMING_X, 260.0, -EGO_YAW, 260.0 - LANE_IN_START_Y)],
        },
        "connectivity": {
            "lane_in": {"incoming": [], "outgoing": ["turn_left"]},
            "turn_left": {"incoming": ["lane_in"], "outgoing": ["lane_out"]},
            "lane_out": {"incoming": ["turn_left"], "outgoing": []},
            "lane_oncoming": {"incoming": [], "outgoing": []},
        },
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(layers))


def map_file(root: Path) -> Path:
    """scene-0002's map expansion file under ``root``."""
    return root / "maps" / "expansion" / f"{LOCATIONS[1]}.json"


def load_tables(root: Path) -> dict[str, object]:
    """Every table of the dataset under ``root``, by name (``sample_data``, ...)."""
    return {p.stem: json.loads(p.read_text()) for p in sorted((root / VERSION).glob("*.json"))}


def edit_table(root: Path, table: str, edit: Callable[[list], object]) -> None:
    """Rewrite ``table`` with ``edit(rows)``: its return value, or the rows it changed in place (None)."""
    path = root / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    changed = edit(rows)
    path.write_text(json.dumps(rows if changed is None else changed))


def copy_with_tables(base: Path, dest: Path, tables: dict[str, object], layers: object = None) -> Path:
    """A dataroot at ``dest`` with ``tables`` (and ``layers`` as scene-0002's map expansion, when
    given), sharing ``base``'s sensor files through links; returns ``dest``."""
    (dest / VERSION).mkdir(parents=True)
    for folder in ("samples", "sweeps", "maps") if layers is None else ("samples", "sweeps"):
        (dest / folder).symlink_to(base / folder, target_is_directory=True)
    for name, rows in tables.items():
        (dest / VERSION / f"{name}.json").write_text(json.dumps(rows))
    if layers is not None:
        map_file(dest).parent.mkdir(parents=True)
        map_file(dest).write_text(json.dumps(layers))
        (dest / "maps" / "mini.png").symlink_to(base / "maps" / "mini.png")  # the map table's raster
    return dest
