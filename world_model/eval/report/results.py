"""The report's typed results and their report.json form.

A :class:`Report` holds one :class:`RowScores` per row: Table 1 (:class:`GenerationScores`),
Table 2 (:class:`YesFrequencies`), the breakdowns (per object category, per camera view, per
clip's chunk jumps), one :class:`LongHorizon` per long clip, the scene IoU per second
(:class:`SceneIoUScores`) and what a policy reads (:class:`DecisionScores`). ``to_json`` writes the keys of
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
class SectorFigures(_FlatScores):
    """One beam band's LiDAR sector readings (:func:`~world_model.eval.decisions.sector_range_errors`):
    ``objects`` (frame, sector) pairs whose recording holds an object within range, the absolute
    range error of those the row also reports, and shares of the objects (``farther_or_missed``,
    ``missed``) or of the empty sectors (``phantom``)."""

    objects: int = 0
    error_p50_m: float | None = None
    error_p95_m: float | None = None
    farther_or_missed: float | None = None  # more than FAR_ERROR_M farther, or no return at all
    missed: float | None = None
    phantom: float | None = None  # the row reports an object where the recording has none


@dataclass(frozen=True)
class LeadFigures(_FlatScores):
    """The lead vehicle in FRONT (:func:`~world_model.eval.decisions.lead_errors`): pixel errors of
    its bottom row and centre column where both the row and the recording show one; the implied
    range error of the recording's ``near_leads`` (within OBJECT_RANGE_M on the flat road) and the
    share of those the row puts more than FAR_ERROR_M farther or misses; ``phantom``: the share of
    frames without a lead where the row shows one."""

    leads: int = 0
    missed: float | None = None
    bottom_row_p50_px: float | None = None
    bottom_row_p95_px: float | None = None
    centre_col_p50_px: float | None = None
    centre_col_p95_px: float | None = None
    near_leads: int = 0
    range_p50_m: float | None = None
    range_p95_m: float | None = None
    near_farther_or_missed: float | None = None
    phantom: float | None = None


@dataclass(frozen=True)
class LaneFigures(_FlatScores):
    """Lane markings at the bottom of FRONT (:func:`~world_model.eval.decisions.lane_errors`):
    ``markings`` (frame, side) pairs whose recording shows one, the lateral error where the row
    shows one too, and the share it misses."""

    markings: int = 0
    error_p50_m: float | None = None
    error_p95_m: float | None = None
    missed: float | None = None


@dataclass(frozen=True)
class DecisionFigures:
    """What a policy reads, over some frames: the LiDAR sectors per beam band (empty for a row
    without LiDAR), the lead vehicle and the lane markings."""

    sectors: Mapping[str, SectorFigures]
    lead: LeadFigures
    lanes: LaneFigures

    def to_json(self) -> dict[str, Any]:
        return {
            "sectors": {band: f.to_json() for band, f in self.sectors.items()},
            "lead": self.lead.to_json(),
            "lanes": self.lanes.to_json(),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DecisionFigures:
        def get(key: str) -> Any:
            return _require(data, key, "decisions")

        return cls(
            sectors={band: SectorFigures.from_json(f) for band, f in get("sectors").items()},
            lead=LeadFigures.from_json(get("lead")),
            lanes=LaneFigures.from_json(get("lanes")),
        )


@dataclass(frozen=True)
class DecisionScores:
    """A row's "what a policy reads" (report.json's ``decisions``): over every frame read of every
    clip, and per whole second pooled over the clips that last that long."""

    overall: DecisionFigures
    per_second: tuple[DecisionFigures, ...]

    def to_json(self) -> dict[str, Any]:
        return {"overall": self.overall.to_json(), "per_second": [s.to_json() for s in self.per_second]}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DecisionScores:
        return cls(
            overall=DecisionFigures.from_json(_require(data, "overall", "decisions")),
            per_second=tuple(DecisionFigures.from_json(s) for s in _require(data, "per_second", "decisions")),
        )


@dataclass(frozen=True)
class RowSpread:
    """Standard deviation over noise seeds of a seeded row's Table 1, Table 2, per-view scores,
    scene IoU and what a policy reads (None when a seed has none)."""

    table1: GenerationScores
    table2: YesFrequencies
    per_view: PerView
    scene_iou: SceneIoUScores | None = None
    decisions: DecisionScores | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "table1": self.table1.to_json(),
            "table2": self.table2.to_json(),
            "per_view": _views_json(self.per_view),
        }
        if self.scene_iou is not None:
            out["scene_iou"] = self.scene_iou.to_json()
        if self.decisions is not None:
            out["decisions"] = self.decisions.to_json()
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RowSpread:
        scene, decisions = data.get("scene_iou"), data.get("decisions")
        return cls(
            GenerationScores.from_json(_require(data, "table1", "spread")),
            YesFrequencies.from_json(_require(data, "table2", "spread")),
            _views(_require(data, "per_view", "spread")),
            None if scene is None else SceneIoUScores.from_json(scene),
            None if decisions is None else DecisionScores.from_json(decisions),
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
    decisions: DecisionScores | None = None  # None where no clip was read (rows built by hand)
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
        if self.decisions is not None:
            out["decisions"] = self.decisions.to_json()
        if self.seeds is not None:
            out["seeds"] = self.seeds
        if self.spread is not None:
            out["spread"] = self.spread.to_json()
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RowScores:
        def get(key: str) -> Any:
            return _require(data, key, "report row")

        spread, scene, decisions = data.get("spread"), get("scene_iou"), data.get("decisions")
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
            decisions=None if decisions is None else DecisionScores.from_json(decisions),
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
