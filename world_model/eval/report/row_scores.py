"""A row's scores pooled over its clips' :class:`ClipScores` (:func:`row_scores`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from world_model.eval.decisions import P50, P95, DecisionSums, LaneSums, LeadSums, SectorSums, percentile, share
from world_model.eval.decisions import pool_seconds as pool_decision_seconds
from world_model.eval.metrics import ChangeSums, ConfusionSums, JumpSums, clip_window_features, frechet_features
from world_model.eval.report.clip_scores import ClipScores, SensorPairs, StreamPair, chunk_jump_scores, motion_scores
from world_model.eval.report.config import ReportConfig
from world_model.eval.report.judging import per_category, per_view, yes_frequencies
from world_model.eval.report.results import (
    HEADLINE_IOU,
    ClipChunkJumps,
    ClipSceneIoU,
    DecisionFigures,
    DecisionScores,
    GenerationScores,
    JumpRatios,
    LaneFigures,
    LeadFigures,
    RowScores,
    SceneIoUScores,
    SectorFigures,
)
from world_model.eval.scene_iou import pool_scene_iou, pool_seconds
from world_model.eval.segmenter import SCENE_CLASSES


def row_scores(clips: Sequence[ClipScores], config: ReportConfig, gt_features: Sequence[np.ndarray] = ()) -> RowScores:
    """Pool one row's per-clip scores: frame scores average over every scored frame of every clip,
    the Fréchet distances compare all scored frames (windows) at once, motion and chunk-jump sums
    add (a long clip weighs by its lagged pairs and pass boundaries), the judge's answers pool.
    ``gt_features``: the recording's judge frame features per clip, when the judge has them."""
    if not clips:
        raise ValueError("row_scores needs the scores of at least one clip")
    scored, lidar_scored = slice(None, None, config.frame_stride), slice(None, None, config.lidar_stride)
    with_lidar = [c for c in clips if c.lidar_mae_per_frame is not None]
    answers = [a for c in clips for a in c.answers]
    jumps = pooled_jumps(clips)
    scene = scene_iou_scores(clips)
    table1 = GenerationScores(
        **frechet_scores(clips, gt_features, config),
        psnr_db=float(np.mean(np.concatenate([c.psnr_per_frame[scored] for c in clips]))),
        ssim=float(np.mean(np.concatenate([c.ssim_scored for c in clips]))),
        lidar_range_mae_m=_mean([m for c in with_lidar for m in c.lidar_mae_per_frame[lidar_scored]]),
        lidar_range_mae_first_s_m=_mean([m for c in with_lidar for m in c.lidar_mae_per_frame[: round(c.fps)]]),
        lidar_chamfer_m=_mean([d for c in clips for d in c.chamfers]),
        object_psnr_db=_mean([p for c in clips for p in c.object_psnrs]),
        lidar_object_mae_m=_mean([m for c in clips for m in c.object_maes]),
        lidar_road_mae_m=_mean([m for c in clips for m in c.road_maes]),
        **{f"{c}_iou": None if scene is None else scene.overall[c] for c in HEADLINE_IOU},
        **chunk_jump_scores(jumps),
        **motion_scores(pooled_motion(clips)),
    )
    return RowScores(
        table1=table1,
        table2=yes_frequencies(answers),
        chunk_jumps={s: JumpRatios(p.generated.ratio(), p.recording.ratio()) for s, p in jumps.items()},
        chunk_jumps_per_clip=tuple(
            ClipChunkJumps(c.clip, **chunk_jump_scores(c.jumps)) for c in clips if c.jumps is not None
        ),
        per_category=per_category(answers),
        per_view=per_view(answers),
        answers=len(answers),
        long_horizon=tuple(c.long_horizon for c in clips if c.long_horizon is not None),
        scene_iou=scene,
        decisions=decision_scores(clips),
    )


def scene_iou_scores(clips: Sequence[ClipScores]) -> SceneIoUScores | None:
    """A row's scene IoU from its clips of at least a second: per class overall, per second pooled
    over the clips that last that long, over the last window of the long clips (those with a
    long-horizon score) and per clip; None without a clip of a second."""
    scored = [c for c in clips if c.scene_iou is not None]
    if not scored:
        return None
    seconds = pool_seconds([c.scene_iou for c in scored])  # clips of any length: their last windows differ
    overall = sum(seconds, ConfusionSums.zeros(len(SCENE_CLASSES)))
    long_clips = [c.scene_iou for c in scored if c.long_horizon is not None]
    return SceneIoUScores(
        overall=dict(zip(SCENE_CLASSES, overall.iou(), strict=True)),
        per_second=tuple(dict(zip(SCENE_CLASSES, s.iou(), strict=True)) for s in seconds),
        last_window_long_clips=pool_scene_iou(long_clips).last_window_iou() if long_clips else None,
        per_clip=tuple(ClipSceneIoU(c.clip, tuple(c.scene_iou.per_second_iou())) for c in scored),
    )


def decision_scores(clips: Sequence[ClipScores]) -> DecisionScores | None:
    """A row's "what a policy reads" from its clips' readings: pooled over every frame read of every
    clip, and per whole second over the clips that last that long; None where no clip was read."""
    read = [c.decisions for c in clips if c.decisions is not None]
    if not read:
        return None
    overall = sum((d.overall for d in read), DecisionSums())
    return DecisionScores(decision_figures(overall), tuple(decision_figures(s) for s in pool_decision_seconds(read)))


def decision_figures(sums: DecisionSums) -> DecisionFigures:
    """The report's figures (percentiles, shares) of pooled readings."""
    return DecisionFigures(
        sectors={band: sector_figures(s) for band, s in sums.sectors.items()},
        lead=lead_figures(sums.lead),
        lanes=lane_figures(sums.lanes),
    )


def sector_figures(s: SectorSums) -> SectorFigures:
    return SectorFigures(
        objects=s.objects,
        error_p50_m=percentile(s.errors_m, P50),
        error_p95_m=percentile(s.errors_m, P95),
        farther_or_missed=share(s.farther + s.missed, s.objects),
        missed=share(s.missed, s.objects),
        phantom=share(s.phantom, s.empty),
    )


def lead_figures(s: LeadSums) -> LeadFigures:
    return LeadFigures(
        leads=s.leads,
        missed=share(s.missed, s.leads),
        bottom_row_p50_px=percentile(s.bottom_row_errors_px, P50),
        bottom_row_p95_px=percentile(s.bottom_row_errors_px, P95),
        centre_col_p50_px=percentile(s.centre_col_errors_px, P50),
        centre_col_p95_px=percentile(s.centre_col_errors_px, P95),
        near_leads=s.near_leads,
        range_p50_m=percentile(s.range_errors_m, P50),
        range_p95_m=percentile(s.range_errors_m, P95),
        near_farther_or_missed=share(s.near_farther + s.near_missed, s.near_leads),
        phantom=share(s.phantom, s.no_lead),
    )


def lane_figures(s: LaneSums) -> LaneFigures:
    return LaneFigures(
        markings=s.markings,
        error_p50_m=percentile(s.errors_m, P50),
        error_p95_m=percentile(s.errors_m, P95),
        missed=share(s.missed, s.markings),
    )


def frechet_scores(
    clips: Sequence[ClipScores], gt_features: Sequence[np.ndarray], config: ReportConfig
) -> dict[str, float | None]:
    """Table 1's Fréchet distances on judge features: of every scored frame, and of every window of
    ``clip_window`` frames (clips shorter than a window left out). None without features."""
    out: dict[str, float | None] = {"frechet_judge_frame": None, "frechet_judge_clip": None}
    feats = [c.features for c in clips]
    if not gt_features or any(f is None for f in feats):
        return out
    if len(gt_features) != len(clips):
        raise ValueError(f"gt_features holds {len(gt_features)} clips' features for {len(clips)} clips")
    scored = slice(None, None, config.frame_stride)
    out["frechet_judge_frame"] = frechet_features(
        np.concatenate([f[scored] for f in feats]), np.concatenate([f[scored] for f in gt_features])
    )
    w = config.clip_window
    long_enough = [i for i, f in enumerate(feats) if len(f) >= w]
    if long_enough:
        out["frechet_judge_clip"] = frechet_features(
            np.concatenate([clip_window_features(feats[i], w) for i in long_enough]),
            np.concatenate([clip_window_features(gt_features[i], w) for i in long_enough]),
        )
    return out


def pooled_motion(clips: Sequence[ClipScores]) -> SensorPairs[ChangeSums]:
    """Every clip's lagged-change sums added up, per sensor."""
    return _pooled([c.motion for c in clips], ChangeSums)


def pooled_jumps(clips: Sequence[ClipScores]) -> SensorPairs[JumpSums]:
    """The chunk-jump sums of the clips generated in passes added up, per sensor."""
    return _pooled([c.jumps for c in clips if c.jumps is not None], JumpSums)


def _pooled(per_clip: Sequence[SensorPairs], empty: type) -> SensorPairs:
    out: dict[str, StreamPair] = {}
    for pairs in per_clip:
        for sensor, pair in pairs.items():
            out[sensor] = out.get(sensor, StreamPair(empty(), empty())) + pair
    return out


def _mean(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None
