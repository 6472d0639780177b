"""The report's typed results and their report.json form.

A :class:`Report` holds one :class:`RowScores` per row: Table 1 (:class:`GenerationScores`),
Table 2 (:class:`YesFrequencies`), the breakdowns (per object category, per camera view, per
clip's chunk jumps), one :class:`LongHorizon` per long clip and the scene IoU per second
(:class:`SceneIoUScores`). ``to_json`` writes the keys of
report.json; ``from_json`` reads them back (the row cache stores rows this way).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any, TypeVar

from world_model.eval.report.config import ReportConfig

F = TypeVar("F", bound="_FlatScores")


def _require(data: Mapping[str, Any], key: str, what: str) -> Any:
    if key not in data:
        raise ValueError(f"{what} has no {key!r}: not a report row of this version (keys: {sorted(data)})")
    return data[key]


class _FlatScores:
    """Scores that are a flat set of named numbers (None where not measured)."""

    def to_json(self) -> dict[str, float | None]:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_json(cls: type[F], data: Mapping[str, Any]) -> F:
        return cls(**{f.name: _require(data, f.name, cls.__name__) for f in fields(cls)})  # type: ignore[arg-type]


@dataclass(frozen=True)
class GenerationScores(_FlatScores):
    """Table 1 (report.json's ``table1``): how close the row's sensors are to the recording.

    Fréchet distances are on the judge's frame features (not Inception FID/FVD); chunk jumps are
    the change into a generation pass's first frame over the change within a pass, relative to the
    recording (1 = as smooth as the recording); motion is the change over ``motion_lag_s`` relative
    to the recording (1 = moves as much, 0 = frozen)."""

    frechet_judge_frame: float | None = None
    frechet_judge_clip: float | None = None
    psnr_db: float | None = None
    ssim: float | None = None
    lidar_range_mae_m: float | None = None
    lidar_range_mae_first_s_m: float | None = None
    lidar_chamfer_m: float | None = None
    object_psnr_db: float | None = None  # over the recording's object pixels only
    lidar_object_mae_m: float | None = None  # over the recording's object returns only
    lidar_road_mae_m: float | None = None  # over the recording's other returns (road and ground)
    road_iou: float | None = None  # scene IoU of the headline classes (SceneIoUScores.overall)
    marking_iou: float | None = None
    vehicle_iou: float | None = None
    chunk_jump_cameras: float | None = None
    chunk_jump_lidar: float | None = None
    motion_cameras: float | None = None
    motion_lidar: float | None = None


@dataclass(frozen=True)
class YesFrequencies(_FlatScores):
    """Table 2 (report.json's ``table2``): the fraction of the judge's yes per question type
    (None where the question was never asked). Fields in :data:`questions.QUESTION_TYPES` order."""

    weather: float | None = None
    time_of_day: float | None = None
    existence: float | None = None
    clarity: float | None = None
    visual_fidelity: float | None = None
    textual_fidelity: float | None = None
    cross_view_consistency: float | None = None

    def of(self, question: str) -> float | None:
        if question not in _QUESTIONS:
            raise ValueError(f"unknown question type {question!r}; one of {_QUESTIONS}")
        return getattr(self, question)


_QUESTIONS = tuple(f.name for f in fields(YesFrequencies))


@dataclass(frozen=True)
class JumpRatios:
    """Chunk-jump ratio of one sensor pooled over a row's clips: the row's stream and the recording's
    at the same frames (report.json's ``chunk_jumps[sensor]``)."""

    generated: float | None
    recording: float | None


@dataclass(frozen=True)
class ClipChunkJumps:
    """One clip's chunk-jump scores (report.json's ``chunk_jumps_per_clip`` entries)."""

    clip: str
    chunk_jump_cameras: float | None
    chunk_jump_lidar: float | None


@dataclass(frozen=True)
class WindowFrechet:
    """Frame Fréchet distance of the first and of the last long-horizon window to the recording's same window."""

    first: float
    last: float
    ratio: float | None  # last / first; None when the first window matches exactly


@dataclass(frozen=True)
class LongHorizon:
    """Stability of one long clip's rollout: per-second curves and the last window against the first."""

    clip: str
    seconds: int
    psnr_per_second: tuple[float, ...]
    ratio_last_first: float  # PSNR of the last window over the first: 1 = no degradation
    frechet: WindowFrechet | None = None  # None without judge features
    lidar_mae_per_second: tuple[float, ...] | None = None  # None for rows without LiDAR
    motion_cameras: float | None = None
    motion_lidar: float | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "clip": self.clip,
            "seconds": self.seconds,
            "psnr_per_second": list(self.psnr_per_second),
            "ratio_last_first": self.ratio_last_first,
        }
        if self.frechet is not None:
            out |= {
                "frechet_judge_frame_first": self.frechet.first,
                "frechet_judge_frame_last": self.frechet.last,
                "frechet_ratio_last_first": self.frechet.ratio,
            }
        if self.lidar_mae_per_second is not None:
            out["lidar_mae_per_second"] = list(self.lidar_mae_per_second)
        return out | {"motion_cameras": self.motion_cameras, "motion_lidar": self.motion_lidar}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> LongHorizon:
        frechet = None
        if "frechet_judge_frame_first" in data:
            frechet = WindowFrechet(
                data["frechet_judge_frame_first"], data["frechet_judge_frame_last"], data["frechet_ratio_last_first"]
            )
        lidar = data.get("lidar_mae_per_second")
        return cls(
            clip=_require(data, "clip", "long_horizon entry"),
            seconds=_require(data, "seconds", "long_horizon entry"),
            psnr_per_second=tuple(_require(data, "psnr_per_second", "long_horizon entry")),
            ratio_last_first=_require(data, "ratio_last_first", "long_horizon entry"),
            frechet=frechet,
            lidar_mae_per_second=None if lidar is None else tuple(lidar),
            motion_cameras=_require(data, "motion_cameras", "long_horizon entry"),
            motion_lidar=_require(data, "motion_lidar", "long_horizon entry"),
        )


PerView = Mapping[str, tuple[float | None, ...]]  # scene question -> yes-frequency of each camera view
ClassIoU = Mapping[str, float | None]  # scene class -> IoU (None where neither labelled nor predicted)
# The scene classes whose IoU Table 1 shows (every class is in the row's ``scene_iou``).
HEADLINE_IOU = ("road", "marking", "vehicle")


@dataclass(frozen=True)
class ClipSceneIoU:
    """One clip's scene IoU per whole second."""

    clip: str
    per_second: tuple[ClassIoU, ...]


@dataclass(frozen=True)
class SceneIoUScores:
    """A row's scene IoU (report.json's ``scene_iou``) over its clips of at least a second: per
    class overall, per second pooled over the clips that last that long, over the last window of
    the long clips (None without one) and per clip."""

    overall: ClassIoU
    per_second: tuple[ClassIoU, ...]
    last_window_long_clips: ClassIoU | None
    per_clip: tuple[ClipSceneIoU, ...]

    def to_json(self) -> dict[str, Any]:
        last = self.last_window_long_clips
        return {
            "overall": dict(self.overall),
            "per_second": [dict(s) for s in self.per_second],
            "last_window_long_clips": None if last is None else dict(last),
            "per_clip": [{"clip": c.clip, "per_second": [dict(s) for s in c.per_second]} for c in self.per_clip],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SceneIoUScores:
        def get(key: str) -> Any:
            return _require(data, key, "scene_iou")

        last = get("last_window_long_clips")
        return cls(
            overall=dict(get("overall")),
            per_second=tuple(dict(s) for s in get("per_second")),
            last_window_long_clips=None if last is None else dict(last),
            per_clip=tuple(ClipSceneIoU(c["clip"], tuple(dict(s) for s in c["per_second"])) for c in get("per_clip")),
        )


@dataclass(frozen=True)
class RowSpread:
    """Standard deviation over noise seeds of a seeded row's Table 1, Table 2, per-view scores and
    scene IoU (None when a seed has none)."""

    table1: GenerationScores
    table2: YesFrequencies
    per_view: PerView
    scene_iou: SceneIoUScores | None = None

    def to_json(self) -> dict[str, Any]:
        out = {
            "table1": self.table1.to_json(),
            "table2": self.table2.to_json(),
            "per_view": _views_json(self.per_view),
        }
        return out if self.scene_iou is None else out | {"scene_iou": self.scene_iou.to_json()}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RowSpread:
        scene = data.get("scene_iou")
        return cls(
            GenerationScores.from_json(_require(data, "table1", "spread")),
            YesFrequencies.from_json(_require(data, "table2", "spread")),
            _views(_require(data, "per_view", "spread")),
            None if scene is None else SceneIoUScores.from_json(scene),
        )


@dataclass(frozen=True)
class RowScores:
    """Everything the report says about one row (one report.json ``rows`` entry).

    ``per_category``: {object question: {category: yes-frequency}}. ``answers``: how many questions
    the judge answered. A row of several noise seeds holds their mean, their count in ``seeds``
    and each score's standard deviation in ``spread`` (:func:`~world_model.eval.report.seeds.average_seeds`);
    a row of one generator has neither."""

    table1: GenerationScores = GenerationScores()
    table2: YesFrequencies = YesFrequencies()
    chunk_jumps: Mapping[str, JumpRatios] = field(default_factory=dict)  # sensor -> pooled ratios
    chunk_jumps_per_clip: tuple[ClipChunkJumps, ...] = ()  # clips generated in passes only
    per_category: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    per_view: PerView = field(default_factory=dict)
    answers: int = 0
    long_horizon: tuple[LongHorizon, ...] = ()  # clips of at least twice long_window_s
    scene_iou: SceneIoUScores | None = None  # None without a clip of at least a second
    seeds: int | None = None
    spread: RowSpread | None = None

    def to_json(self) -> dict[str, Any]:
        out = {
            "table1": self.table1.to_json(),
            "chunk_jumps": {sensor: asdict(r) for sensor, r in self.chunk_jumps.items()},
            "chunk_jumps_per_clip": [asdict(c) for c in self.chunk_jumps_per_clip],
            "table2": self.table2.to_json(),
            "per_category": {q: dict(cats) for q, cats in self.per_category.items()},
            "per_view": _views_json(self.per_view),
            "answers": self.answers,
            "long_horizon": [c.to_json() for c in self.long_horizon],
            "scene_iou": None if self.scene_iou is None else self.scene_iou.to_json(),
        }
        if self.seeds is not None:
            out["seeds"] = self.seeds
        if self.spread is not None:
            out["spread"] = self.spread.to_json()
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RowScores:
        def get(key: str) -> Any:
            return _require(data, key, "report row")

        spread, scene = data.get("spread"), get("scene_iou")
        return cls(
            table1=GenerationScores.from_json(get("table1")),
            table2=YesFrequencies.from_json(get("table2")),
            chunk_jumps={sensor: JumpRatios(**r) for sensor, r in get("chunk_jumps").items()},
            chunk_jumps_per_clip=tuple(ClipChunkJumps(**c) for c in get("chunk_jumps_per_clip")),
            per_category={q: dict(cats) for q, cats in get("per_category").items()},
            per_view=_views(get("per_view")),
            answers=get("answers"),
            long_horizon=tuple(LongHorizon.from_json(c) for c in get("long_horizon")),
            scene_iou=None if scene is None else SceneIoUScores.from_json(scene),
            seeds=data.get("seeds"),
            spread=None if spread is None else RowSpread.from_json(spread),
        )


@dataclass(frozen=True)
class Report:
    """Every row's scores on the same clips under the same :class:`ReportConfig` (report.json)."""

    rows: Mapping[str, RowScores]
    clips: tuple[str, ...]
    config: ReportConfig = ReportConfig()

    def to_json(self) -> dict[str, Any]:
        rows = {name: r.to_json() for name, r in self.rows.items()}
        return {"rows": rows, "clips": list(self.clips), "config": self.config.to_json()}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Report:
        rows = _require(data, "rows", "report")
        return cls(
            rows={name: RowScores.from_json(r) for name, r in rows.items()},
            clips=tuple(_require(data, "clips", "report")),
            config=ReportConfig(**_require(data, "config", "report")),
        )


def _views(data: Mapping[str, Any]) -> PerView:
    return {q: tuple(freqs) for q, freqs in data.items()}


def _views_json(views: PerView) -> dict[str, list[float | None]]:
    return {q: list(freqs) for q, freqs in views.items()}
