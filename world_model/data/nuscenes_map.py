"""The nuScenes map expansion (``maps/expansion/<location>.json``) read as JSON: the drawn map near a
logged path, and the lanes the logged ego drove along, as one centerline.

The file is read with ``json`` (no shapely); lane centerlines come from its ``arcline_path_3`` layer
through the devkit's ``arcline_path_utils.discretize_lane`` (pure Python). Coordinates are the
nuScenes global frame (x east, y north). Every layer read here is checked when the file is read
(:func:`check_layers`), before the devkit sees any of it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from world_model.data.nuscenes_tables import (
    MAX_COORDINATE_M,
    Check,
    NuScenesFormatError,
    check_rows,
    field_error,
    finite_number,
    finite_numbers,
    text_field,
    token_field,
)
from world_model.scene import LaneLine, MapGeometry

# Half-width of the drivable corridor drawn along the logged ego path, metres.
CORRIDOR_HALF_WIDTH_M = 5.0
CENTERLINE_STEP_M = 0.5  # discretization of the arcline paths
# A logged pose belongs to a lane when it is this close to the lane's centerline and heads its way.
MAX_LANE_DISTANCE_M = 3.0
MAX_LANE_HEADING_RAD = math.radians(45.0)
HEADING_COST_M_PER_RAD = 2.0  # between two candidate lanes, 1 rad of heading counts as 2 m of distance
ROUTE_EXTENSION_M = 60.0  # connected lanes added before the first and after the last driven lane
DEFAULT_LANE_WIDTH_M = 3.5  # when no route lane has a polygon to measure
LANE_WIDTH_RANGE_M = (2.5, 6.0)
MIN_ARC_RADIUS_M = 0.1  # an arcline path's turning radius (the devkit divides by it)
MAX_LANE_LENGTH_M = 10_000.0  # an arcline path's length (the devkit makes a pose every CENTERLINE_STEP_M)


class MapExpansionError(NuScenesFormatError):
    """A map expansion file that cannot be read (its path, and the layer, row and field, are in the message)."""


def _coordinate(value: object) -> str | None:
    x = finite_number(value)
    return None if x is not None and abs(x) <= MAX_COORDINATE_M else f"a finite number within ±{MAX_COORDINATE_M:g} m"


def _tokens(value: object) -> str | None:
    ok = isinstance(value, list) and all(isinstance(t, str) for t in value)
    return None if ok else "a list of token strings"


def _pose(value: object) -> str | None:
    pose = finite_numbers(value, 3)
    ok = pose and abs(pose[0]) <= MAX_COORDINATE_M and abs(pose[1]) <= MAX_COORDINATE_M
    return None if ok else f"3 finite numbers (x, y, yaw), x and y within ±{MAX_COORDINATE_M:g} m"


def _radius(value: object) -> str | None:
    r = finite_number(value)
    return None if r is not None and r >= MIN_ARC_RADIUS_M else f"a finite number of metres >= {MIN_ARC_RADIUS_M:g}"


def _segment_lengths(value: object) -> str | None:
    lengths = finite_numbers(value, 3)
    ok = lengths and min(lengths) >= 0 and sum(lengths) <= MAX_LANE_LENGTH_M
    return None if ok else f"3 finite numbers >= 0 of metres, at most {MAX_LANE_LENGTH_M:g} m together"


# The layers read here (lists of rows), the fields read of their rows, and the layers those fields' tokens name.
LAYER_FIELDS: dict[str, dict[str, Check]] = {
    "node": {"token": token_field, "x": _coordinate, "y": _coordinate},
    "polygon": {"token": token_field, "exterior_node_tokens": _tokens},
    "line": {"token": token_field, "node_tokens": _tokens},
    "drivable_area": {"polygon_tokens": _tokens},
    "lane_divider": {"line_token": token_field},
    "road_divider": {"line_token": token_field},
    "lane": {"token": token_field},
    "lane_connector": {"token": token_field},
}
OPTIONAL_LAYERS = ("lane_connector",)
LAYER_REFERENCES = {
    ("polygon", "exterior_node_tokens"): "node",
    ("line", "node_tokens"): "node",
    ("drivable_area", "polygon_tokens"): "polygon",
    ("lane_divider", "line_token"): "line",
    ("road_divider", "line_token"): "line",
}
ARCLINE_FIELDS: dict[str, Check] = {
    "start_pose": _pose,
    "shape": text_field,
    "radius": _radius,
    "segment_length": _segment_lengths,
}


def check_layers(path: Path, layers: object) -> dict:
    """``layers`` when every layer read here holds what it should (:data:`LAYER_FIELDS`, each token
    naming a row of its layer, the ``arcline_path_3`` paths and the ``connectivity``), else
    :class:`MapExpansionError` naming the file, the layer, the row and the field."""
    try:
        if not isinstance(layers, dict):
            raise MapExpansionError(f"{path}: a map expansion is a JSON object of layers, got {type(layers).__name__}")
        for layer, fields in LAYER_FIELDS.items():
            if layer not in layers and layer not in OPTIONAL_LAYERS:
                raise MapExpansionError(f"{path}: layer {layer!r} is missing")
            check_rows(f"{path}: layer {layer!r}", layers.get(layer, []), fields, {"polygon_token": text_field})
        tokens = {layer: {r["token"] for r in layers[layer]} for layer in ("node", "polygon", "line")}
        for (layer, field), target in LAYER_REFERENCES.items():
            for i, row in enumerate(layers[layer]):
                named = row[field] if isinstance(row[field], list) else [row[field]]
                if missing := [t for t in named if t not in tokens[target]]:
                    allowed = f"{missing[0]!r} is no token of layer {target!r}"
                    raise field_error(f"{path}: layer {layer!r}", row, field, allowed, i)
        _check_arclines(path, layers.get("arcline_path_3", {}))
        _check_connectivity(path, layers.get("connectivity", {}))
    except MapExpansionError:
        raise
    except NuScenesFormatError as e:  # check_rows' message, which names the file and the layer
        raise MapExpansionError(str(e)) from None
    return layers


def _check_arclines(path: Path, arclines: object) -> None:
    if not isinstance(arclines, dict):
        raise MapExpansionError(f"{path}: layer 'arcline_path_3' is a JSON object (lane token -> arcline paths)")
    for token, paths in arclines.items():
        check_rows(f"{path}: layer 'arcline_path_3' lane {token!r}", paths, ARCLINE_FIELDS)


def _check_connectivity(path: Path, links: object) -> None:
    ok = isinstance(links, dict) and all(
        isinstance(v, dict) and all(_tokens(v.get(d, [])) is None for d in ("incoming", "outgoing"))
        for v in links.values()
    )
    if not ok:
        raise MapExpansionError(
            f"{path}: layer 'connectivity' is a JSON object: lane token -> {{'incoming': [...], 'outgoing': [...]}}"
        )


@lru_cache(maxsize=2)
def _layers(path: Path) -> dict:
    """The file's checked layers, read once per process (a real map expansion is tens of megabytes)."""
    try:
        layers = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as e:
        raise MapExpansionError(f"map expansion {path} is not readable: {e!r}") from e
    return check_layers(path, layers)


def map_layers(dataroot: str | Path, location: str) -> tuple[Path, dict] | None:
    """``(path, layers)`` of ``maps/expansion/<location>.json``; None when the file is absent."""
    path = Path(dataroot) / "maps" / "expansion" / f"{location}.json"
    return (path, _layers(path)) if path.exists() else None


def corridor_map(path_xy: np.ndarray, half_width: float = CORRIDOR_HALF_WIDTH_M) -> MapGeometry:
    """A drivable corridor along a logged path: its area, and its two edges as road edges."""
    if len(path_xy) < 2:
        path_xy = np.concatenate([path_xy, path_xy + [[0.1, 0.0]]])
    d = np.gradient(path_xy, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1)
    left, right = path_xy + half_width * normal, path_xy - half_width * normal
    return MapGeometry(
        road_edges=(left, right),
        drivable_area=(np.concatenate([left, right[::-1]]),),
        lane_width=2 * half_width,
    )


def map_expansion(dataroot: str | Path, location: str, path_xy: np.ndarray, margin: float) -> MapGeometry | None:
    """The map expansion's drivable area (its outlines as road edges), lane dividers (dashed) and
    road dividers (solid) whose bounding box comes within ``margin`` metres of the path's; None when
    the file is absent. Polygon holes are not kept."""
    found = map_layers(dataroot, location)
    if found is None:
        return None
    path, layers = found
    nodes = {n["token"]: (n["x"], n["y"]) for n in layers["node"]}
    polygons = {p["token"]: p["exterior_node_tokens"] for p in layers["polygon"]}
    lines = {ln["token"]: ln["node_tokens"] for ln in layers["line"]}
    areas = [polygons[t] for a in layers["drivable_area"] for t in a["polygon_tokens"]]
    dividers = [(lines[d["line_token"]], "dashed") for d in layers["lane_divider"]]
    dividers += [(lines[d["line_token"]], "solid") for d in layers["road_divider"]]
    lo, hi = path_xy.min(axis=0) - margin, path_xy.max(axis=0) + margin

    def near(tokens: list[str]) -> np.ndarray | None:
        pts = np.array([nodes[t] for t in tokens], dtype=np.float64)
        # Bounding boxes overlap: a large polygon around the path counts though no vertex is near.
        overlaps = len(pts) >= 2 and np.all(pts.max(axis=0) >= lo) and np.all(pts.min(axis=0) <= hi)
        return pts if overlaps else None

    drivable = tuple(p for p in (near(a) for a in areas) if p is not None)
    lane_lines = tuple(LaneLine(points=p, kind=k) for p, k in ((near(t), k) for t, k in dividers) if p is not None)
    edges = tuple(np.concatenate([p, p[:1]]) for p in drivable)
    return MapGeometry(lane_lines=lane_lines, road_edges=edges, drivable_area=drivable)


@dataclass(frozen=True)
class MapRoute:
    """The lanes (and lane connectors) the logged ego drove along, joined into one centerline."""

    lanes: tuple[str, ...]  # lane tokens in driving order, the connected extensions included
    centerline: np.ndarray  # (N, 2) global frame
    lane_width: float  # median over the route's lanes of polygon area / centerline length


def _centerlines(layers: dict, path: Path, lo: np.ndarray, hi: np.ndarray) -> dict[str, np.ndarray]:
    """(N, 3) x, y, yaw poses of every lane's centerline whose bounding box meets [lo, hi]."""
    from nuscenes.map_expansion.arcline_path_utils import discretize_lane

    if "arcline_path_3" not in layers:
        raise MapExpansionError(f"{path}: layer 'arcline_path_3' is missing (the lanes' centerlines)")
    arclines = layers["arcline_path_3"]
    out = {}
    for token in (r["token"] for r in (*layers["lane"], *layers.get("lane_connector", []))):
        if not arclines.get(token):
            continue
        try:  # the paths are checked (check_layers): this is a guard, not a filter
            poses = np.array(discretize_lane(arclines[token], CENTERLINE_STEP_M), dtype=np.float64)
        except (KeyError, TypeError, ValueError, AssertionError, ArithmeticError) as e:
            raise MapExpansionError(f"{path}: layer 'arcline_path_3' lane {token!r} is not readable: {e!r}") from e
        if not np.all(np.isfinite(poses)):
            raise MapExpansionError(f"{path}: layer 'arcline_path_3' lane {token!r} gives non-finite centerline poses")
        if np.all(poses[:, :2].max(axis=0) >= lo) and np.all(poses[:, :2].min(axis=0) <= hi):
            out[token] = poses
    return out


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _nearest_index(poses: np.ndarray, x: float, y: float) -> tuple[int, float]:
    d = np.hypot(poses[:, 0] - x, poses[:, 1] - y)
    k = int(np.argmin(d))
    return k, float(d[k])


def _extend(
    lanes: list[str], centerlines: dict[str, np.ndarray], links: dict, direction: str, length: float
) -> list[str]:
    """Lanes linked to the end (``outgoing``) or start (``incoming``) of ``lanes``, straightest first."""
    added: list[str] = []
    total, current = 0.0, lanes[-1] if direction == "outgoing" else lanes[0]
    while total < length:
        options = [t for t in links.get(current, {}).get(direction, []) if t in centerlines and t not in lanes + added]
        if not options:
            break
        here = centerlines[current][-1 if direction == "outgoing" else 0, 2]
        nxt = min(options, key=lambda t: abs(_wrap(centerlines[t][0 if direction == "outgoing" else -1, 2] - here)))
        added.append(nxt)
        total += float(np.hypot(*np.diff(centerlines[nxt][:, :2], axis=0).T).sum())
        current = nxt
    return added if direction == "outgoing" else added[::-1]


def _lane_width(layers: dict, lanes: list[str], centerlines: dict[str, np.ndarray]) -> float:
    nodes = {n["token"]: (n["x"], n["y"]) for n in layers.get("node", [])}
    polygons = {p["token"]: p["exterior_node_tokens"] for p in layers.get("polygon", [])}
    records = {r["token"]: r for r in (*layers["lane"], *layers.get("lane_connector", []))}
    widths = []
    for token in lanes:
        ring = polygons.get(records[token].get("polygon_token", ""))
        if not ring or any(t not in nodes for t in ring):
            continue
        p = np.array([nodes[t] for t in ring], dtype=np.float64)
        area = 0.5 * abs(float(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1))))
        length = float(np.hypot(*np.diff(centerlines[token][:, :2], axis=0).T).sum())
        if length > 1.0:
            widths.append(area / length)
    return float(np.clip(np.median(widths), *LANE_WIDTH_RANGE_M)) if widths else DEFAULT_LANE_WIDTH_M


def map_route(dataroot: str | Path, location: str, poses: np.ndarray) -> MapRoute | None:
    """The route of logged ego ``poses`` ((T, 3) x, y, yaw) along the map's lanes, or None when the map
    expansion is absent or some pose is on no lane (farther than ``MAX_LANE_DISTANCE_M`` from every
    centerline heading within ``MAX_LANE_HEADING_RAD`` of it).

    Each pose takes its nearest lane (distance plus ``HEADING_COST_M_PER_RAD`` per radian of heading
    difference). Consecutive lanes that the map connects are joined whole; between lanes it does not
    connect (a lane change) the centerline leaves the first where the ego was last on it and joins the
    second where the ego was first on it. Connected lanes extend the route ``ROUTE_EXTENSION_M``
    before the start and after the end (the straightest continuation)."""
    found = map_layers(dataroot, location)
    if found is None:
        return None
    path, layers = found
    reach = MAX_LANE_DISTANCE_M + ROUTE_EXTENSION_M
    centerlines = _centerlines(layers, path, poses[:, :2].min(axis=0) - reach, poses[:, :2].max(axis=0) + reach)
    visits: list[tuple[str, int, int]] = []  # (lane, first pose index, last pose index) in order
    sample_at: dict[tuple[str, int], int] = {}  # (lane, pose index) -> nearest centerline sample
    for i, (x, y, yaw) in enumerate(poses):
        best, best_cost = None, math.inf
        for token, line in centerlines.items():
            k, dist = _nearest_index(line, x, y)
            turn = abs(float(_wrap(line[k, 2] - yaw)))
            cost = dist + HEADING_COST_M_PER_RAD * turn
            if dist <= MAX_LANE_DISTANCE_M and turn <= MAX_LANE_HEADING_RAD and cost < best_cost:
                best, best_cost = (token, k), cost
        if best is None:
            return None
        sample_at[(best[0], i)] = best[1]
        if visits and visits[-1][0] == best[0]:
            visits[-1] = (best[0], visits[-1][1], i)
        else:
            visits.append((best[0], i, i))
    links = layers.get("connectivity", {})
    driven = [v[0] for v in visits]
    pieces = []
    for j, (token, first, last) in enumerate(visits):
        line = centerlines[token][:, :2]
        joined_before = j == 0 or token in links.get(visits[j - 1][0], {}).get("outgoing", [])
        joined_after = j == len(visits) - 1 or visits[j + 1][0] in links.get(token, {}).get("outgoing", [])
        start = 0 if joined_before else sample_at[(token, first)]
        end = len(line) if joined_after else sample_at[(token, last)] + 1
        pieces.append(line[start:end])
    before = _extend(driven, centerlines, links, "incoming", ROUTE_EXTENSION_M)
    after = _extend(driven, centerlines, links, "outgoing", ROUTE_EXTENSION_M)
    centerline = np.concatenate(
        [*(centerlines[t][:, :2] for t in before), *pieces, *(centerlines[t][:, :2] for t in after)]
    )
    keep = np.concatenate([[True], np.hypot(*np.diff(centerline, axis=0).T) > 1e-3])
    lanes = [*before, *driven, *after]
    return MapRoute(lanes=tuple(lanes), centerline=centerline[keep], lane_width=_lane_width(layers, lanes, centerlines))
