"""Evaluation (paper §8-§9): the judge, quality metrics and the report tables.

* :mod:`~world_model.eval.crops`: projected-box crops with the paper's (scaled) size filter.
* :mod:`~world_model.eval.judge`: the :class:`JudgeBackend` question interface and the default
  CNN backend (:func:`load_default_judge`); :mod:`~world_model.eval.train_judge` trains it.
* :mod:`~world_model.eval.metrics`: PSNR, SSIM, judge-feature Fréchet distances, LiDAR errors,
  long-horizon curves, inter-chunk jumps, motion.
* :mod:`~world_model.eval.report`: rows (callables ``Clip -> Generated``) to Table 1 / Table 2 and
  the quality bars, one module per concern (rows, scoring, cache, markdown, bars).
"""

from world_model.eval.crops import CropConfig, ObjectCrop, crop_boxes, extract_crops, group_by_track_time
from world_model.eval.judge import CnnJudge, JudgeBackend, JudgeThresholds, load_default_judge, load_judge
from world_model.eval.metrics import (
    chamfer_distance,
    chunk_jumps,
    frechet_distance,
    frechet_judge_clip,
    frechet_judge_frame,
    lagged_change,
    lidar_range_mae,
    long_horizon_ratio,
    motion_ratio,
    per_second_curve,
    psnr,
    ssim,
)
from world_model.eval.report import Generated, evaluate_rows, format_markdown, oracle_row, write_report

__all__ = [
    "CnnJudge",
    "CropConfig",
    "Generated",
    "JudgeBackend",
    "JudgeThresholds",
    "ObjectCrop",
    "chamfer_distance",
    "chunk_jumps",
    "crop_boxes",
    "evaluate_rows",
    "extract_crops",
    "format_markdown",
    "frechet_distance",
    "frechet_judge_clip",
    "frechet_judge_frame",
    "group_by_track_time",
    "lagged_change",
    "lidar_range_mae",
    "load_default_judge",
    "load_judge",
    "long_horizon_ratio",
    "motion_ratio",
    "oracle_row",
    "per_second_curve",
    "psnr",
    "ssim",
    "write_report",
]
