"""Evaluation (paper §8-§9): the judge, quality metrics and the report tables.

* :mod:`~world_model.eval.crops`: projected-box crops with the paper's (scaled) size filter.
* :mod:`~world_model.eval.judge`: the :class:`JudgeBackend` question interface and the default
  CNN backend (:func:`load_default_judge`); :mod:`~world_model.eval.train_judge` trains it.
* :mod:`~world_model.eval.metrics`: PSNR, SSIM, judge-feature Fréchet distances, per-class pixel
  sums (IoU), LiDAR errors, long-horizon curves, inter-chunk jumps, motion.
* :mod:`~world_model.eval.segmenter`: the scene classes and the small segmentation network
  (:func:`load_default_segmenter`); :mod:`~world_model.eval.train_segmenter` trains it and
  :mod:`~world_model.eval.scene_iou` scores generated frames with it against label maps.
* :mod:`~world_model.eval.report`: rows (callables ``Clip -> Generated``) to Table 1 / Table 2, the
  scene IoU and the quality bars, one module per concern (rows, scoring, cache, markdown, bars).
"""

from world_model.eval.crops import CropConfig, ObjectCrop, crop_boxes, extract_crops, group_by_track_time
from world_model.eval.judge import CnnJudge, JudgeBackend, JudgeThresholds, load_default_judge, load_judge
from world_model.eval.metrics import (
    chamfer_distance,
    chunk_jumps,
    confusion_sums,
    frechet_distance,
    frechet_judge_clip,
    frechet_judge_frame,
    lagged_change,
    lidar_range_mae,
    lidar_region_errors,
    long_horizon_ratio,
    motion_ratio,
    per_second_curve,
    psnr,
    ssim,
)
from world_model.eval.report import Generated, evaluate_rows, format_markdown, oracle_row, write_report
from world_model.eval.scene_iou import SceneIoU, pool_scene_iou, scene_iou, scene_labels
from world_model.eval.segmenter import SCENE_CLASSES, Segmenter, load_default_segmenter, load_segmenter

__all__ = [
    "SCENE_CLASSES",
    "CnnJudge",
    "CropConfig",
    "Generated",
    "JudgeBackend",
    "JudgeThresholds",
    "ObjectCrop",
    "SceneIoU",
    "Segmenter",
    "chamfer_distance",
    "chunk_jumps",
    "confusion_sums",
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
    "lidar_region_errors",
    "load_default_judge",
    "load_default_segmenter",
    "load_judge",
    "load_segmenter",
    "long_horizon_ratio",
    "motion_ratio",
    "oracle_row",
    "per_second_curve",
    "pool_scene_iou",
    "psnr",
    "scene_iou",
    "scene_labels",
    "ssim",
    "write_report",
]
