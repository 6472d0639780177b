"""A :class:`Report` as markdown: Table 1, Table 2, their breakdowns, what a policy reads and the quality bars."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import fields

import numpy as np

from world_model.eval.decisions import FAR_ERROR_M, OBJECT_RANGE_M, SECTOR_DEG
from world_model.eval.report.bars import check_bars, format_score
from world_model.eval.report.results import (
    HEADLINE_IOU,
    DecisionFigures,
    DecisionScores,
    GenerationScores,
    LongHorizon,
    Report,
    YesFrequencies,
)

LONG_HORIZON_COLUMNS = (
    "seconds",
    "ratio_last_first",
    "frechet_judge_frame_first",
    "frechet_judge_frame_last",
    "frechet_ratio_last_first",
    "motion_cameras",
    "motion_lidar",
)


def format_markdown(report: Report) -> str:
    """Every table of ``report`` as one markdown document."""
    table1 = [f.name for f in fields(GenerationScores)]
    lines = ["### Table 1: generation quality (judge-feature Fréchet distances, not Inception FID/FVD)", ""]
    lines += table(table1, [[row] + [format_score(getattr(r.table1, k)) for k in table1]
                            for row, r in report.rows.items()])  # fmt: skip
    questions = [f.name for f in fields(YesFrequencies)]
    lines += ["", "### Table 2: controllability (judge yes-frequencies)", ""]
    lines += table(questions, [[row] + [format_score(r.table2.of(q)) for q in questions]
                               for row, r in report.rows.items()])  # fmt: skip
    lines += existence_by_category(report)
    lines += scene_by_view(report)
    lines += scene_iou_by_second(report)
    lines += what_a_policy_reads(report)
    lines += what_a_policy_reads_by_second(report)
    lines += long_horizon_table(report)
    lines += chunk_jumps_per_clip(report)
    lines += quality_bars(report)
    return "\n".join(lines) + "\n"


def table(columns: Sequence[str], rows: Sequence[Sequence[str]], first: Sequence[str] = ("row",)) -> list[str]:
    """Markdown lines of a table whose rows start with the cells named ``first``."""
    header = [*first, *columns]
    return ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"] + [
        "| " + " | ".join(cells) + " |" for cells in rows
    ]


def scene_iou_by_second(report: Report) -> list[str]:
    """Markdown lines: each row's scene IoU (road, marking, vehicle) per second, pooled over the
    clips that last that long, and over the last window of the long clips: a rollout that loses its
    road shows it here at the second it happens. Empty without a clip of a second."""
    rows = {row: r.scene_iou for row, r in report.rows.items() if r.scene_iou is not None}
    if not rows:
        return []
    seconds = max(len(v.per_second) for v in rows.values())
    w = report.config.long_window_s
    cells = []
    for row, v in rows.items():
        for c in HEADLINE_IOU:
            per_s = [format_score(s.get(c), 2) for s in v.per_second] + [""] * (seconds - len(v.per_second))
            cells.append([row, c, *per_s, format_score((v.last_window_long_clips or {}).get(c), 2)])
    lines = ["", "### Scene IoU per second (segmenter on the generated views against the recording's labels)", ""]
    columns = [f"{k}s" for k in range(seconds)] + [f"last {w} s (long clips)"]
    return lines + table(columns, cells, first=("row", "class"))


def _horizon_farther_or_missed(d: DecisionFigures) -> float | None:
    horizon = d.sectors.get("horizon")
    return None if horizon is None else horizon.farther_or_missed


# The per-second table's figures: the horizon beams' far objects, the lead's bottom row, the lane.
PER_SECOND_DECISIONS: tuple[tuple[str, Callable[[DecisionFigures], float | None]], ...] = (
    ("LiDAR horizon: farther or missed", _horizon_farther_or_missed),
    ("lead bottom row p50 px", lambda d: d.lead.bottom_row_p50_px),
    ("lane lateral p50 m", lambda d: d.lanes.error_p50_m),
)
LIDAR_COLUMNS = ("objects", "abs error p50 / p95 m", f">{FAR_ERROR_M:g} m farther or missed", "missed", "phantom")
FRONT_COLUMNS = (
    "leads",
    "lead missed",
    "bottom row p50 / p95 px",
    "centre column p50 / p95 px",
    "near leads",
    "range p50 / p95 m",
    f">{FAR_ERROR_M:g} m farther or missed",
    "phantom lead",
    "markings",
    "lateral p50 / p95 m",
    "marking missed",
)


def _decision_rows(report: Report) -> dict[str, DecisionScores]:
    return {row: r.decisions for row, r in report.rows.items() if r.decisions is not None}


def _p50_p95(p50: float | None, p95: float | None, digits: int = 2) -> str:
    return f"{format_score(p50, digits)} / {format_score(p95, digits)}"


def what_a_policy_reads(report: Report) -> list[str]:
    """Markdown lines: each row's readings that change a driving decision, against the recording's
    (:mod:`world_model.eval.decisions`): the LiDAR's nearest object per sector and beam band, the
    lead vehicle and the lane markings in FRONT. Empty where no row was read."""
    rows = _decision_rows(report)
    if not rows:
        return []
    lidar, front = [], []
    for row, d in rows.items():
        for band, f in d.overall.sectors.items():
            lidar.append([row, band, str(f.objects), _p50_p95(f.error_p50_m, f.error_p95_m)]
                         + [format_score(v) for v in (f.farther_or_missed, f.missed, f.phantom)])  # fmt: skip
        lead, lanes = d.overall.lead, d.overall.lanes
        front.append([
            row, str(lead.leads), format_score(lead.missed),
            _p50_p95(lead.bottom_row_p50_px, lead.bottom_row_p95_px, 1),
            _p50_p95(lead.centre_col_p50_px, lead.centre_col_p95_px, 1),
            str(lead.near_leads), _p50_p95(lead.range_p50_m, lead.range_p95_m),
            format_score(lead.near_farther_or_missed), format_score(lead.phantom),
            str(lanes.markings), _p50_p95(lanes.error_p50_m, lanes.error_p95_m), format_score(lanes.missed),
        ])  # fmt: skip
    lines = ["", "### What a policy reads (the row's sensors against the recording's)", ""]
    lines.append(
        f"LiDAR: the nearest return above the road in each {SECTOR_DEG:g}° sector where the recording has one "
        f"within {OBJECT_RANGE_M:g} m (an object); shares of those objects (phantom: of the other sectors)."
    )
    lines += [""] + table(LIDAR_COLUMNS, lidar, first=("row", "band")) + [""]
    lines.append(
        "FRONT (the same segmenter on the row's view and the recording's): the lead vehicle, the largest "
        f"vehicle blob in the central third (near: standing within {OBJECT_RANGE_M:g} m on the flat road), "
        "and the nearest lane marking left and right in the bottom rows."
    )
    return lines + [""] + table(FRONT_COLUMNS, front)


def what_a_policy_reads_by_second(report: Report) -> list[str]:
    """Markdown lines: the headline readings (:data:`PER_SECOND_DECISIONS`) of each row per second,
    pooled over the clips that last that long. Empty where no row was read for a whole second."""
    rows = {row: d for row, d in _decision_rows(report).items() if d.per_second}
    if not rows:
        return []
    seconds = max(len(d.per_second) for d in rows.values())
    cells = []
    for row, d in rows.items():
        for name, figure in PER_SECOND_DECISIONS:
            per_s = [format_score(figure(s), 2) for s in d.per_second] + [""] * (seconds - len(d.per_second))
            cells.append([row, name, *per_s])
    lines = ["", "### What a policy reads per second", ""]
    return lines + table([f"{k}s" for k in range(seconds)], cells, first=("row", "reading"))


def long_horizon_table(report: Report) -> list[str]:
    """Markdown lines: each long clip's last window against its first, per row. Empty without long clips."""
    long_rows = [(row, c) for row, r in report.rows.items() for c in r.long_horizon]
    if not long_rows:
        return []
    w = report.config.long_window_s
    lines = ["", f"### Long horizon: last {w} s vs first {w} s of each long clip", ""]
    return lines + table(
        LONG_HORIZON_COLUMNS,
        [[row, c.clip] + [format_score(v) for v in _long_horizon_cells(c)] for row, c in long_rows],
        first=("row", "clip"),
    )


def _long_horizon_cells(c: LongHorizon) -> tuple[float | None, ...]:
    f = c.frechet
    return (
        c.seconds,
        c.ratio_last_first,
        None if f is None else f.first,
        None if f is None else f.last,
        None if f is None else f.ratio,
        c.motion_cameras,
        c.motion_lidar,
    )


def chunk_jumps_per_clip(report: Report, reference: str = "student") -> list[str]:
    """Markdown: the spread over clips of each row's chunk-jump scores, and on how many clips a
    row jumps more than the ``reference`` row (when present), per sensor."""
    rows = {row: r.chunk_jumps_per_clip for row, r in report.rows.items() if r.chunk_jumps_per_clip}
    if not rows:
        return []
    ref = {c.clip: c for c in rows.get(reference, ())}
    scored = any(v is not None for c in ref.values() for v in (c.chunk_jump_cameras, c.chunk_jump_lidar))
    above_ref = f", above {reference}" if scored else ""
    cells = []
    for row, clips in rows.items():
        line = [row, str(len(clips))]
        for sensor in ("cameras", "lidar"):
            key = f"chunk_jump_{sensor}"
            v = np.array([getattr(c, key) for c in clips if getattr(c, key) is not None])
            if not len(v):
                line.append("n/a")
                continue
            pairs = [(getattr(c, key), getattr(ref[c.clip], key)) for c in clips if c.clip in ref]
            pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
            above = f", {sum(a > b for a, b in pairs)} of {len(pairs)}" if pairs and row != reference else ""
            line.append(f"{np.median(v):.3f} ({v.min():.3f}-{v.max():.3f}){above}")
        cells.append(line)
    columns = ["clips"] + [f"{s}: median (min-max){above_ref}" for s in ("cameras", "lidar")]
    return ["", "### Chunk jumps per clip", ""] + table(columns, cells)


def existence_by_category(report: Report) -> list[str]:
    """Markdown lines: the existence yes-frequency of each object category per row (how a rare
    object, e.g. a LoRA case, fares apart from the common ones). Empty when no object was judged."""
    rows = report.rows
    cats = sorted({c for r in rows.values() for c in r.per_category.get("existence", {})})
    if not cats:
        return []
    cells = [
        [row] + [format_score(r.per_category.get("existence", {}).get(c)) for c in cats] for row, r in rows.items()
    ]
    return ["", "### Existence per object category (judge yes-frequencies)", ""] + table(cats, cells)


def scene_by_view(report: Report) -> list[str]:
    """Markdown lines: weather and time-of-day yes-frequencies of each camera view per row (a model
    whose side views turn to night shows it here, not averaged away). Empty without per-view answers."""
    rows = {row: r.per_view for row, r in report.rows.items() if r.per_view}
    if not rows:
        return []
    views = max(len(v) for r in rows.values() for v in r.values())
    cells = [[row, q] + [format_score(f) for f in freqs] for row, r in rows.items() for q, freqs in r.items()]
    lines = ["", "### Weather and time of day per camera view (judge yes-frequencies)", ""]
    return lines + table([f"view {k}" for k in range(views)], cells, first=("row", "question"))


def quality_bars(report: Report, model: str = "student") -> list[str]:
    """Markdown lines: the quality bars of ``model`` (:func:`bars.check_bars`); empty without an
    ``oracle`` and a ``model`` row."""
    checks = check_bars(report, model)
    if not checks:
        return []
    lines = ["", f"### Quality bars ({model})", ""]
    return lines + table(
        ["measured", "status", "autoencoder (ceiling)"],
        [[c.bar, c.measured, c.status, c.ceiling] for c in checks],
        first=("bar",),
    )
