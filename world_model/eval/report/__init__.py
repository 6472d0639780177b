"""The evaluation report (paper §9): rows -> Table 1 (frame / clip Fréchet distances on judge
features, PSNR, SSIM, LiDAR and object errors, chunk jumps, motion) and Table 2 (judge
yes-frequencies), as markdown and report.json. One module per concern:

* :mod:`.rows`: what is evaluated. A row is a callable ``Clip -> Generated`` (the Oracle, the
  reference rows, the streamed student, the autoencoder, the teacher).
* :mod:`.lineup`: which rows a bundle's report runs, under which streaming settings, with the
  ids their cached scores are keyed by; :func:`report_bundle` runs it all (``m4world eval --report``).
* :mod:`.judging`: Table 2's questions asked of a row's frames, and their yes-frequencies.
* :mod:`.clip_scores`: one clip's measurements (:class:`ClipScores`, the scene IoU and what a
  policy reads included) against the recording's side (:class:`ClipTruth`); :mod:`.row_scores`
  pools them into a row's :class:`RowScores`; :mod:`.seeds` averages a row over noise seeds.
* :mod:`.results`: the typed results and their report.json form.
* :mod:`.cache`: finished rows on disk, keyed by row id, clips, config, judge, segmenter and version.
* :mod:`.run`: :func:`evaluate_rows` (rows x clips -> :class:`Report`) and :func:`write_report`.
* :mod:`.markdown`: the tables; :mod:`.bars`: the quality bars' thresholds and pass/fail.
"""

from world_model.eval.report.bars import BarCheck, QualityBars, check_bars, scene_iou_bar
from world_model.eval.report.config import ReportConfig
from world_model.eval.report.lineup import BundleReport, ReportRequest, StudentStreaming, report_bundle
from world_model.eval.report.markdown import format_markdown
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
    LongHorizon,
    Report,
    RowScores,
    RowSpread,
    SceneIoUScores,
    SectorFigures,
    WindowFrechet,
    YesFrequencies,
)
from world_model.eval.report.rows import Generated, RowFn, first_frame_row, oracle_row, road_only_row
from world_model.eval.report.run import evaluate_rows, write_report

__all__ = [
    "HEADLINE_IOU",
    "BarCheck",
    "BundleReport",
    "ClipChunkJumps",
    "ClipSceneIoU",
    "DecisionFigures",
    "DecisionScores",
    "Generated",
    "GenerationScores",
    "JumpRatios",
    "LaneFigures",
    "LeadFigures",
    "LongHorizon",
    "QualityBars",
    "Report",
    "ReportConfig",
    "ReportRequest",
    "RowFn",
    "RowScores",
    "RowSpread",
    "SceneIoUScores",
    "SectorFigures",
    "StudentStreaming",
    "WindowFrechet",
    "YesFrequencies",
    "check_bars",
    "evaluate_rows",
    "first_frame_row",
    "format_markdown",
    "oracle_row",
    "report_bundle",
    "road_only_row",
    "scene_iou_bar",
    "write_report",
]
