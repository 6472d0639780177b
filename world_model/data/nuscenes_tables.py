"""nuScenes' JSON tables, read and checked row by row before the importer uses any of them.

Every table the importer reads (:data:`TABLE_FIELDS`) must be a JSON list of objects, each row
holding the fields the importer reads, with values of the right type and within range: tokens
that name a row of the table they point into, finite numbers, unit quaternions, positive box
sizes, camera intrinsics with positive focal lengths. :func:`scene_chains` checks one scene's
chains (its samples, each sensor's sample_data): timestamps strictly increase along them, and the
first keyframe holds LIDAR_TOP and the six cameras. A value that breaks a rule raises
:class:`NuScenesFormatError`, naming the table file, the row's token, the field and the value.
Fields the importer does not read are not checked.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from world_model.sensors import DEFAULT_CAMERA_NAMES

LIDAR_CHANNEL = "LIDAR_TOP"
CAMERA_CHANNELS = tuple(f"CAM_{name}" for name in DEFAULT_CAMERA_NAMES)
MICROSECONDS = 1e-6

# Bounds of the values the importer reads: beyond them a value is corrupt, not a log.
MAX_TIMESTAMP_US = 2**53  # every integer up to it is exact in float64
# nuScenes scenes last 20 s; every frame of a clip is held in memory until the clip is written.
MAX_SCENE_DURATION_S = 600.0
MAX_COORDINATE_M = 1e6  # global poses and box centres (a nuScenes map spans a few km)
MAX_SENSOR_OFFSET_M = 50.0  # a calibrated sensor sits on the vehicle
MAX_OBJECT_SIZE_M = 100.0  # an annotated box's width, length or height
MAX_PIXELS = 100_000  # an image side, a focal length or a principal point coordinate
QUATERNION_NORM_TOLERANCE = 1e-3
# Scene names and locations become file names (clip folders, map expansion files).
FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
SHOWN_VALUE_CHARS = 80  # a refused value is shown up to this many characters


class NuScenesImportError(ValueError):
    """A nuScenes dataroot, version, scene or sample file that cannot be imported."""


class NuScenesFormatError(NuScenesImportError):
    """A table file, row or field that breaks the schema the importer reads (the message names
    the table file, the row's token, the field and the value)."""


Check = Callable[[object], "str | None"]  # None: the value is allowed; else what is allowed


def finite_number(value: object) -> float | None:
    """``value`` as a float when it is a finite JSON number (a bool is not one), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:  # an integer beyond the float range
        return None
    return number if math.isfinite(number) else None


def finite_numbers(value: object, length: int) -> list[float] | None:
    """``value`` as floats when it is a list of ``length`` finite numbers, else None."""
    if not isinstance(value, list) or len(value) != length:
        return None
    numbers = [finite_number(v) for v in value]
    return None if None in numbers else numbers  # type: ignore[return-value]


def text_field(value: object) -> str | None:
    return None if isinstance(value, str) else "a string"


def token_field(value: object) -> str | None:
    return None if isinstance(value, str) and value else "a non-empty string"


def _file_name(value: object) -> str | None:
    ok = isinstance(value, str) and FILE_NAME.fullmatch(value)
    return None if ok else "a name of letters, digits, '.', '_' and '-' that does not start with '.' (it names a file)"


def _flag(value: object) -> str | None:
    return None if isinstance(value, bool) else "true or false"


def _timestamp(value: object) -> str | None:
    t = finite_number(value)
    return None if t is not None and 0 <= t <= MAX_TIMESTAMP_US else "a finite number of microseconds in [0, 2^53]"


def _image_side(value: object) -> str | None:
    ok = isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_PIXELS
    return None if ok else f"an integer number of pixels in [0, {MAX_PIXELS}]"


def _translation(bound: float) -> Check:
    def check(value: object) -> str | None:
        xyz = finite_numbers(value, 3)
        return None if xyz and all(abs(v) <= bound for v in xyz) else f"3 finite numbers within ±{bound:g} m"

    return check


def _size(value: object) -> str | None:
    wlh = finite_numbers(value, 3)
    ok = wlh and all(0 < v <= MAX_OBJECT_SIZE_M for v in wlh)
    return None if ok else f"3 numbers in (0, {MAX_OBJECT_SIZE_M:g}] m (width, length, height)"


def _quaternion(value: object) -> str | None:
    q = finite_numbers(value, 4)
    ok = q and abs(math.sqrt(sum(v * v for v in q)) - 1.0) <= QUATERNION_NORM_TOLERANCE
    return None if ok else f"4 finite numbers (w, x, y, z) of unit norm (within {QUATERNION_NORM_TOLERANCE:g})"


def _intrinsic(value: object) -> str | None:
    """[] (not a camera) or a 3x3 matrix with positive focal lengths."""
    if value == []:
        return None
    rows = [finite_numbers(r, 3) for r in value] if isinstance(value, list) and len(value) == 3 else [None]
    ok = None not in rows and all(abs(v) <= MAX_PIXELS for r in rows for v in r)  # type: ignore[union-attr]
    if ok and rows[0][0] > 0 and rows[1][1] > 0:  # type: ignore[index]
        return None
    return f"[] or a 3x3 matrix of finite numbers within ±{MAX_PIXELS} px, its focal lengths (K[0][0], K[1][1]) > 0"


@dataclass(frozen=True)
class Ref:
    """A field holding the token of a row of ``table``; "" where ``optional`` (a chain's end)."""

    table: str
    optional: bool = False

    def __call__(self, value: object) -> str | None:
        return text_field(value) if self.optional else token_field(value)


# The fields the importer reads, per table, and what each may hold.
TABLE_FIELDS: dict[str, dict[str, Check]] = {
    "category": {"token": token_field, "name": text_field},
    "instance": {"token": token_field, "category_token": Ref("category")},
    "sensor": {"token": token_field, "channel": text_field},
    "calibrated_sensor": {
        "token": token_field,
        "sensor_token": Ref("sensor"),
        "translation": _translation(MAX_SENSOR_OFFSET_M),
        "rotation": _quaternion,
        "camera_intrinsic": _intrinsic,
    },
    "ego_pose": {"token": token_field, "translation": _translation(MAX_COORDINATE_M), "rotation": _quaternion},
    "log": {"token": token_field, "location": _file_name},
    "scene": {"token": token_field, "name": _file_name, "first_sample_token": Ref("sample"), "log_token": Ref("log")},
    "sample": {
        "token": token_field,
        "timestamp": _timestamp,
        "next": Ref("sample", optional=True),
    },
    "sample_data": {
        "token": token_field,
        "sample_token": Ref("sample"),
        "ego_pose_token": Ref("ego_pose"),
        "calibrated_sensor_token": Ref("calibrated_sensor"),
        "timestamp": _timestamp,
        "is_key_frame": _flag,
        "filename": token_field,
        "width": _image_side,
        "height": _image_side,
        "prev": Ref("sample_data", optional=True),
        "next": Ref("sample_data", optional=True),
    },
    "sample_annotation": {
        "token": token_field,
        "sample_token": Ref("sample"),
        "instance_token": Ref("instance"),
        "translation": _translation(MAX_COORDINATE_M),
        "size": _size,
        "rotation": _quaternion,
    },
}
OPTIONAL_FIELDS: dict[str, dict[str, Check]] = {"scene": {"description": text_field}}


def _show(value: object) -> str:
    text = repr(value)
    return text if len(text) <= SHOWN_VALUE_CHARS else text[: SHOWN_VALUE_CHARS - 3] + "..."


def _json_type(value: object) -> str:
    kinds = ((dict, "an object"), (str, "a string"), (bool, "a boolean"), (int | float, "a number"), (list, "a list"))
    return next((name for kind, name in kinds if isinstance(value, kind)), "null")


def _row_name(row: dict, index: int) -> str:
    token = row.get("token")
    return repr(token) if isinstance(token, str) and token else f"#{index}"


def field_error(where: str | Path, row: dict, field: str, allowed: str, index: int = 0) -> NuScenesFormatError:
    """The error for ``row[field]`` (row ``index`` when it has no token) of the table ``where``
    (its file, and a layer's name): the value and what is allowed."""
    return NuScenesFormatError(
        f"{where}: row {_row_name(row, index)}: field {field!r} is {_show(row[field])}; {allowed}"
    )


def check_rows(
    where: str, rows: object, fields: dict[str, Check], optional: dict[str, Check] | None = None
) -> list[dict]:
    """``rows`` when it is a list of objects, each holding ``fields`` (and maybe ``optional``) with
    allowed values; else :class:`NuScenesFormatError` starting with ``where`` (the file, the layer)."""
    if not isinstance(rows, list):
        raise NuScenesFormatError(f"{where}: a table is a JSON list of objects (one per row), got {_json_type(rows)}")
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise NuScenesFormatError(f"{where}: row #{i} is {_show(row)}; each row is a JSON object")
        for field, check in fields.items():
            if field not in row:
                raise NuScenesFormatError(f"{where}: row {_row_name(row, i)}: field {field!r} is missing")
            if allowed := check(row[field]):
                raise field_error(where, row, field, f"expected {allowed}", i)
        for field, check in (optional or {}).items():
            if field in row and (allowed := check(row[field])):
                raise field_error(where, row, field, f"expected {allowed}", i)
    return rows


def _read_table(path: Path, fields: dict[str, Check], optional: dict[str, Check]) -> list[dict]:
    try:
        rows = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise NuScenesImportError(f"{path} is missing (the importer reads {', '.join(TABLE_FIELDS)})") from None
    except OSError as e:
        raise NuScenesImportError(f"{path} is not readable: {e}") from e
    except (ValueError, RecursionError) as e:  # ValueError: bad JSON or bad UTF-8
        raise NuScenesFormatError(f"{path} is not valid JSON: {e}") from e
    return check_rows(str(path), rows, fields, optional)


def _index(path: Path, rows: list[dict]) -> dict[str, dict]:
    by_token: dict[str, dict] = {}
    for i, row in enumerate(rows):
        if row["token"] in by_token:
            raise field_error(path, row, "token", "each token names one row of a table", i)
        by_token[row["token"]] = row
    return by_token


@dataclass
class NuScenesTables:
    """The tables of one nuScenes version, checked (:func:`read_tables`), with the reverse indexes
    the importer looks up: each sample's keyframe sample_data per channel, and its annotations."""

    dataroot: Path
    version: str
    rows: dict[str, list[dict]]
    by_token: dict[str, dict[str, dict]]
    key_frames: dict[str, dict[str, dict]]  # sample token -> channel -> keyframe sample_data
    annotations: dict[str, list[dict]]  # sample token -> its sample_annotation rows

    @property
    def scenes(self) -> list[dict]:
        return self.rows["scene"]

    def path(self, table: str) -> Path:
        return self.dataroot / self.version / f"{table}.json"

    def get(self, table: str, token: str) -> dict:
        return self.by_token[table][token]

    def channel(self, sample_data: dict) -> str:
        calibration = self.get("calibrated_sensor", sample_data["calibrated_sensor_token"])
        return self.get("sensor", calibration["sensor_token"])["channel"]

    def category_name(self, annotation: dict) -> str:
        instance = self.get("instance", annotation["instance_token"])
        return self.get("category", instance["category_token"])["name"]


def read_tables(dataroot: Path, version: str) -> NuScenesTables:
    """Read and check the tables the importer uses from ``dataroot/version``: each a JSON list of
    objects, each row's fields present and within range, each token field naming a row."""
    root = Path(dataroot) / version
    rows = {t: _read_table(root / f"{t}.json", f, OPTIONAL_FIELDS.get(t, {})) for t, f in TABLE_FIELDS.items()}
    by_token = {table: _index(root / f"{table}.json", table_rows) for table, table_rows in rows.items()}
    for table, fields in TABLE_FIELDS.items():
        refs = {field: check for field, check in fields.items() if isinstance(check, Ref)}
        for i, row in enumerate(rows[table]):
            for field, ref in refs.items():
                if row[field] not in by_token[ref.table] and (row[field] or not ref.optional):
                    allowed = f"no row of {ref.table}.json has this token" + (' ("": none)' if ref.optional else "")
                    raise field_error(root / f"{table}.json", row, field, allowed, i)
    names: dict[str, dict] = {}
    for i, scene in enumerate(rows["scene"]):
        if scene["name"] in names:
            other = names[scene["name"]]["token"]
            raise field_error(root / "scene.json", scene, "name", f"scene {other!r} has it too (it names a clip)", i)
        names[scene["name"]] = scene
    tables = NuScenesTables(Path(dataroot), version, rows, by_token, {}, {})
    for sd in rows["sample_data"]:
        if sd["is_key_frame"]:
            tables.key_frames.setdefault(sd["sample_token"], {})[tables.channel(sd)] = sd
    for annotation in rows["sample_annotation"]:
        tables.annotations.setdefault(annotation["sample_token"], []).append(annotation)
    return tables


@dataclass(frozen=True)
class SceneChains:
    """One scene's rows in time order: its keyframes, and every sample_data of each channel."""

    samples: list[dict]
    channels: dict[str, list[dict]]  # LIDAR_CHANNEL and CAMERA_CHANNELS
    first: dict[str, dict]  # channel -> the first keyframe's sample_data


def _follow(tables: NuScenesTables, table: str, start: dict, link: str, scene: dict) -> list[dict]:
    """``start`` and the rows its ``link`` ("next" or "prev") leads to, in link order. Timestamps
    must strictly increase in time order, which also makes every chain end."""
    rows = [start]
    while rows[-1][link]:
        row = tables.get(table, rows[-1][link])
        earlier, later = (rows[-1], row) if link == "next" else (row, rows[-1])
        if not later["timestamp"] > earlier["timestamp"]:
            raise field_error(
                tables.path(table),
                later,
                "timestamp",
                f"not after {earlier['timestamp']!r}, the timestamp of {earlier['token']!r} before it in scene "
                f"{scene['name']!r} (timestamps strictly increase along a scene)",
            )
        rows.append(row)
    return rows


def _channel_chain(tables: NuScenesTables, key_frame: dict, channel: str, scene: dict) -> list[dict]:
    before = _follow(tables, "sample_data", key_frame, "prev", scene)
    chain = before[:0:-1] + _follow(tables, "sample_data", key_frame, "next", scene)
    for sd in chain:
        if (found := tables.channel(sd)) != channel:
            allowed = f"a {found} calibration, in the {channel} chain of scene {scene['name']!r}"
            raise field_error(tables.path("sample_data"), sd, "calibrated_sensor_token", allowed)
    return chain


def scene_chains(tables: NuScenesTables, scene: dict) -> SceneChains:
    """Check and collect ``scene``'s keyframes and each channel's sample_data: timestamps strictly
    increase, the samples span at most ``MAX_SCENE_DURATION_S``, the first keyframe holds LIDAR_TOP
    and the six cameras, whose images have a size and calibrations an intrinsic matrix."""
    samples = _follow(tables, "sample", tables.get("sample", scene["first_sample_token"]), "next", scene)
    span_s = (samples[-1]["timestamp"] - samples[0]["timestamp"]) * MICROSECONDS
    if span_s > MAX_SCENE_DURATION_S:
        allowed = (
            f"{span_s:.6g} s after the first sample {samples[0]['token']!r} of scene {scene['name']!r}; "
            f"a scene spans at most {MAX_SCENE_DURATION_S:g} s"
        )
        raise field_error(tables.path("sample"), samples[-1], "timestamp", allowed)
    first = tables.key_frames.get(samples[0]["token"], {})
    channels = {}
    for channel in (LIDAR_CHANNEL, *CAMERA_CHANNELS):
        if channel not in first:
            raise NuScenesFormatError(
                f"{tables.path('sample_data')}: no {channel} keyframe of scene {scene['name']!r}'s first sample "
                f"{samples[0]['token']!r} (sample_token, is_key_frame); the import needs LIDAR_TOP and the six cameras"
            )
        channels[channel] = _channel_chain(tables, first[channel], channel, scene)
    for channel in CAMERA_CHANNELS:
        sd = first[channel]
        for side in ("width", "height"):
            if sd[side] <= 0:
                raise field_error(tables.path("sample_data"), sd, side, f"a {channel} image has at least one pixel")
        calibration = tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
        if calibration["camera_intrinsic"] == []:
            allowed = f"{channel} is a camera: its 3x3 intrinsic matrix is needed"
            raise field_error(tables.path("calibrated_sensor"), calibration, "camera_intrinsic", allowed)
    return SceneChains(samples=samples, channels=channels, first=first)
