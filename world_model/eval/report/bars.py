"""The shipped checkpoint's quality bars: thresholds (:class:`QualityBars`) and each bar's
pass/fail on a report (:func:`check_bars` -> :class:`BarCheck`).

Judge bars compare the model row's yes-frequencies with the ``oracle`` row (a ratio), with a
minimum, view by view for weather and time of day (a view dark as night fails on its own), or with
the ``geometry_only`` baseline (a margin); stability bars read its long-horizon windows and its
first-second LiDAR error; scene IoU bars compare its every second with the ``autoencoder`` row's
(the recording through the VAE). With an ``autoencoder`` row each judge bar also says whether that
ceiling passes it: a bar the ceiling misses is out of reach of any model generating through this VAE.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from world_model.eval.report.results import Report, RowScores, YesFrequencies

JudgeBar = Callable[[YesFrequencies], tuple[str, bool | None]]  # yes-frequencies -> (how measured, met)


@dataclass(frozen=True)
class QualityBars:
    """Thresholds of the quality bars (every default visible)."""

    oracle_ratios: tuple[tuple[str, float], ...] = (("existence", 0.8), ("weather", 0.85), ("time_of_day", 0.85))
    minimums: tuple[tuple[str, float], ...] = (("existence", 0.6),)  # yes-frequency over every question
    view_minimums: tuple[tuple[str, float], ...] = (("time_of_day", 0.9), ("weather", 0.8))  # in every view
    fidelity_margin: float = 0.30  # visual/textual fidelity above the geometry-only baseline
    long_tolerance: float = 0.20  # last vs first long-horizon window, PSNR and Fréchet ratios
    lidar_first_s_max_m: float = 2.0
    # x the autoencoder row's scene IoU at the same second, at every second of every clip
    scene_iou_ratios: tuple[tuple[str, float], ...] = (("road", 0.8), ("vehicle", 0.5))


@dataclass(frozen=True)
class BarCheck:
    """One bar on one report: what it requires, what was measured and whether it is met."""

    bar: str
    measured: str
    met: bool | None  # None: not measured (a row it needs is missing)
    ceiling: str = ""  # the autoencoder row on the same bar; empty where it has none

    @property
    def status(self) -> str:
        return "not measured" if self.met is None else ("met" if self.met else "missed")


def check_bars(report: Report, model: str = "student", bars: QualityBars = QualityBars()) -> list[BarCheck]:
    """Every bar on ``model``'s row. Empty without an ``oracle`` and a ``model`` row."""
    rows = report.rows
    if "oracle" not in rows or model not in rows:
        return []
    oracle = rows["oracle"].table2
    baseline = rows["geometry_only"].table2 if "geometry_only" in rows else None
    ceiling = rows.get("autoencoder")
    scores = rows[model]
    out: list[BarCheck] = []

    def judged(bar: str, judge: JudgeBar, capped: bool = True) -> BarCheck:
        measured, met = judge(scores.table2)
        top = ""
        if ceiling is not None and capped:
            top = ceiling_text(*judge(ceiling.table2))
        return BarCheck(bar, measured, met, top)

    def ratio(q: str, bar: float) -> JudgeBar:
        def judge(t2: YesFrequencies) -> tuple[str, bool | None]:
            v, o = t2.of(q), oracle.of(q)
            r = None if v is None or not o else v / o
            return f"{format_score(v)} / {format_score(o)} = {format_score(r)} x", None if r is None else r >= bar

        return judge

    def margin(q: str) -> JudgeBar:
        def judge(t2: YesFrequencies) -> tuple[str, bool | None]:
            v, base = t2.of(q), None if baseline is None else baseline.of(q)
            d = None if base is None or v is None else v - base
            return (
                f"{format_score(v)} - {format_score(base)} = {format_score(d)}",
                None if d is None else d >= bars.fidelity_margin,
            )

        return judge

    def above(q: str) -> JudgeBar:
        def judge(t2: YesFrequencies) -> tuple[str, bool | None]:
            v, base = t2.of(q), None if baseline is None else baseline.of(q)
            return f"{format_score(v)} vs {format_score(base)}", None if base is None or v is None else v > base

        return judge

    def at_least(q: str, bar: float) -> JudgeBar:
        def judge(t2: YesFrequencies) -> tuple[str, bool | None]:
            v = t2.of(q)
            return format_score(v), None if v is None else v >= bar

        return judge

    for q, bar in bars.oracle_ratios:
        out.append(judged(f"{q} ≥ {bar} x oracle", ratio(q, bar)))
    for q, bar in bars.minimums:
        out.append(judged(f"{q} ≥ {bar}", at_least(q, bar)))
    for q, bar in bars.view_minimums:
        measured, met = worst_view(scores, q, bar)
        reach = "" if ceiling is None else ceiling_text(*worst_view(ceiling, q, bar))
        out.append(BarCheck(f"{q} ≥ {bar} in every camera view", measured, met, reach))
    for q in ("visual_fidelity", "textual_fidelity"):
        out.append(judged(f"{q} ≥ geometry_only + {bars.fidelity_margin:.2f}", margin(q)))
    # No ceiling here: blurrier crops look *more* alike across views, so the VAE does not cap it.
    out.append(judged("cross_view_consistency > geometry_only", above("cross_view_consistency"), capped=False))
    tol = bars.long_tolerance
    for c in scores.long_horizon:
        fr, pr = None if c.frechet is None else c.frechet.ratio, c.ratio_last_first
        met = abs(pr - 1) <= tol and (fr is None or fr <= 1 + tol)
        bar = f"{c.clip}: last vs first window within {tol:.0%} (PSNR, Fréchet)"
        out.append(BarCheck(bar, f"{format_score(pr)}, {format_score(fr)}", met))
    for c, bar in bars.scene_iou_ratios:
        measured, met = scene_iou_bar(scores, ceiling, c, bar)
        out.append(BarCheck(f"{c} IoU ≥ {bar} x autoencoder at every second of every clip", measured, met))
    mae = scores.table1.lidar_range_mae_first_s_m
    met = None if mae is None else mae <= bars.lidar_first_s_max_m
    out.append(BarCheck(f"LiDAR range MAE first second ≤ {bars.lidar_first_s_max_m} m", format_score(mae), met))
    return out


def ceiling_text(measured: str, met: bool | None) -> str:
    """A bar's ceiling column: what the autoencoder row measured and whether it passes."""
    return "" if met is None else f"{measured}: {'reachable' if met else 'out of reach'}"


def worst_view(scores: RowScores, question: str, bar: float) -> tuple[str, bool | None]:
    """The lowest yes-frequency of ``question`` over the row's camera views: (what was measured,
    at least ``bar``?); not measured without per-view answers."""
    views = [(v, k) for k, v in enumerate(scores.per_view.get(question, ())) if v is not None]
    if not views:
        return "", None
    low, k = min(views)
    return f"{format_score(low)} (view {k})", low >= bar


def scene_iou_bar(
    scores: RowScores, ceiling: RowScores | None, scene_class: str, bar: float
) -> tuple[str, bool | None]:
    """The worst second, over every clip, of ``scores``' IoU of ``scene_class`` against the
    ``ceiling`` row's (the autoencoder's) at the same second: (what was measured, met?). Seconds
    where the ceiling never sees the class do not count; not measured without a ceiling or scene IoU."""
    mine, top = scores.scene_iou, None if ceiling is None else ceiling.scene_iou
    if mine is None or top is None:
        return "", None
    worst: tuple[float, str] | None = None
    for ours, theirs in zip(mine.per_clip, top.per_clip, strict=True):
        for k, (a, b) in enumerate(zip(ours.per_second, theirs.per_second, strict=True)):
            if reachable := b.get(scene_class):
                ratio = (a.get(scene_class) or 0.0) / reachable
                if worst is None or ratio < worst[0]:
                    worst = (ratio, f"{ours.clip} second {k}")
    if worst is None:
        return "", None
    return f"worst {format_score(worst[0])} x ({worst[1]})", worst[0] >= bar


def format_score(v: float | None, digits: int = 3) -> str:
    """How the report prints a score: 3 decimals, n/a where not measured."""
    return "n/a" if v is None else f"{v:.{digits}f}"
