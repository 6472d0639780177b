"""Scene IoU: does a generated camera stream still show the recording's road, markings and objects?

The segmenter (:mod:`world_model.eval.segmenter`) labels every pixel of the generated frames; the
ground truth's label maps come from the recording's scene frames (:func:`scene_labels`, the
simulator's geometry, no pixels involved). Per class, IoU is pooled over the pixels of each whole
second of the clip and of its last ``window_s`` seconds. A frame without road or vehicles scores
near 0 on those classes however close its colours are to the recording's. The oracle (the
recording's own frames) scores the segmenter's accuracy, the ceiling of any row.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from world_model.eval.metrics import ConfusionSums, confusion_sums
from world_model.eval.segmenter import NUM_SCENE_CLASSES, SCENE_CLASSES, Segmenter, scene_classes
from world_model.scene import SceneFrame
from world_model.sim.labels import LabelRasterizer


def scene_labels(
    frames: Sequence[SceneFrame], height: int, width: int, rasterizer: LabelRasterizer | None = None
) -> np.ndarray:
    """(T, V, H, W) uint8 :data:`SCENE_CLASSES` ids of every camera of every frame (each frame's
    own rig, rendered at H x W)."""
    if not frames:
        raise ValueError("scene_labels needs at least one frame")
    raster = rasterizer or LabelRasterizer()
    return np.stack([scene_classes(raster(f, f.rig, height, width)) for f in frames])


@dataclass(frozen=True)
class SceneIoU:
    """Per-class pixel sums of one clip (or of several pooled by :func:`pool_scene_iou`)."""

    per_second: tuple[ConfusionSums, ...]  # one per whole second of the clip, in order
    last_window: ConfusionSums  # the last ``window_s`` whole seconds (all of them in a shorter clip)
    window_s: int  # seconds the last window covers

    def per_second_iou(self) -> list[dict[str, float | None]]:
        """Per second: class name -> IoU (None where the class is neither labelled nor predicted)."""
        return [dict(zip(SCENE_CLASSES, s.iou(), strict=True)) for s in self.per_second]

    def last_window_iou(self) -> dict[str, float | None]:
        """Class name -> IoU over the last window."""
        return dict(zip(SCENE_CLASSES, self.last_window.iou(), strict=True))


def scene_iou(
    generated: np.ndarray,
    labels: np.ndarray,
    fps: float,
    segmenter: Segmenter,
    window_s: int = 10,
    frame_stride: int = 1,
) -> SceneIoU:
    """Scene IoU of generated camera frames (T, V, H, W, 3) uint8 against the ground truth's label
    maps (T, V, H, W) of :data:`SCENE_CLASSES` ids (:func:`scene_labels`).

    Frames are grouped by whole seconds (``fps`` frames each, a partial last second dropped, as in
    :func:`~world_model.eval.metrics.per_second_curve`); every ``frame_stride``-th frame is
    segmented (a cost knob: the segmenter runs on the CPU)."""
    step = round(fps)
    if step < 1 or abs(step - fps) > 1e-6:
        raise ValueError(f"fps must be a positive integer rate, got {fps}")
    if window_s < 1 or frame_stride < 1:
        raise ValueError(f"window_s and frame_stride must be >= 1, got {window_s} and {frame_stride}")
    if generated.dtype != np.uint8 or generated.ndim != 5 or generated.shape[-1] != 3:
        raise ValueError(f"generated must be uint8 (T, V, H, W, 3), got {generated.dtype} {generated.shape}")
    if labels.shape != generated.shape[:-1]:
        raise ValueError(f"labels must be {generated.shape[:-1]} (the frames without channels), got {labels.shape}")
    seconds = len(generated) // step
    if seconds == 0:
        raise ValueError(f"need at least one second ({step} frames), got {len(generated)}")
    per_second = []
    for s in range(seconds):
        picked = [t for t in range(s * step, (s + 1) * step) if t % frame_stride == 0]
        predicted = segmenter.predict(np.asarray(generated[picked]))
        per_second.append(confusion_sums(predicted, labels[picked], NUM_SCENE_CLASSES))
    window = min(window_s, seconds)
    last = ConfusionSums.zeros(NUM_SCENE_CLASSES)
    for sums in per_second[-window:]:
        last = last + sums
    return SceneIoU(tuple(per_second), last, window)


def pool_seconds(results: Sequence[SceneIoU]) -> tuple[ConfusionSums, ...]:
    """Several clips' per-second sums pooled by pixels: second k sums every clip that has a second k
    (clips of any length and last window)."""
    if not results:
        raise ValueError("pool_seconds needs at least one result")
    pooled = []
    for k in range(max(len(r.per_second) for r in results)):
        sums = ConfusionSums.zeros(NUM_SCENE_CLASSES)
        for r in results:
            if k < len(r.per_second):
                sums = sums + r.per_second[k]
        pooled.append(sums)
    return tuple(pooled)


def pool_scene_iou(results: Sequence[SceneIoU]) -> SceneIoU:
    """Several clips' scene IoU pooled by pixels: the seconds as :func:`pool_seconds`, and the last
    windows added up. All results must cover the same ``window_s``."""
    if not results:
        raise ValueError("pool_scene_iou needs at least one result")
    windows = {r.window_s for r in results}
    if len(windows) != 1:
        raise ValueError(f"cannot pool last windows of different lengths {sorted(windows)} s")
    last = ConfusionSums.zeros(NUM_SCENE_CLASSES)
    for r in results:
        last = last + r.last_window
    return SceneIoU(pool_seconds(results), last, windows.pop())
