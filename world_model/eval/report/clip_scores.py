"""Scoring one row's sensors on one clip: :func:`score_clip` -> :class:`ClipScores`.

A clip's scores are kept as per-frame values and sums, not as means, because the row's scores
pool over clips (a 60 s clip weighs by its frames, chunk boundaries and lagged pairs):
:func:`~world_model.eval.report.row_scores.row_scores` does the pooling.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from world_model.data import Clip
from world_model.eval.crops import CropConfig
from world_model.eval.decisions import (
    ClipDecisions,
    DecisionSums,
    camera_decisions,
    front_view_index,
    lidar_decisions,
)
from world_model.eval.judge import CnnJudge, JudgeBackend
from world_model.eval.metrics import (
    ChangeSums,
    JumpSums,
    chamfer_distance,
    chunk_jumps,
    frechet_features,
    lagged_change,
    lidar_range_mae,
    lidar_region_errors,
    long_horizon_ratio,
    masked_psnr,
    motion_ratio,
    per_second_curve,
    psnr,
    ssim,
)
from world_model.eval.report.config import ReportConfig
from world_model.eval.report.judging import Answer, judge_clip
from world_model.eval.report.results import LongHorizon, WindowFrechet
from world_model.eval.report.rows import Generated
from world_model.eval.scene_iou import SceneIoU, scene_iou, scene_labels
from world_model.eval.segmenter import Segmenter
from world_model.sim import ProceduralSimulator

S = TypeVar("S", ChangeSums, JumpSums)


@dataclass(frozen=True)
class StreamPair(Generic[S]):
    """One sum over the row's stream and the same sum over the recording at the same frames."""

    generated: S
    recording: S

    def __add__(self, other: StreamPair[S]) -> StreamPair[S]:
        return StreamPair(self.generated + other.generated, self.recording + other.recording)


SensorPairs = Mapping[str, StreamPair[S]]  # sensor ("cameras", "lidar") -> generated / recording


@dataclass(frozen=True, eq=False)
class ClipTruth:
    """What a clip's rows are scored against, computed once per report (:func:`clip_truth`): the
    judge's frame features of the recording (None when the judge has none), the recording's scene
    label maps at the frames the scene IoU reads and, at the same frames, the segmenter's classes of
    its FRONT view (what a policy reads is read by the same segmenter on the row and the recording)."""

    features: np.ndarray | None  # (T, D)
    scene_labels: np.ndarray  # (T, V, H, W) uint8 scene class ids; 0 at the frames not read
    front_classes: np.ndarray | None = None  # (T, H, W) uint8; None without a FRONT view or a segmenter


def clip_truth(clip: Clip, judge: JudgeBackend, config: ReportConfig, segmenter: Segmenter | None = None) -> ClipTruth:
    """The recording's side of ``clip``'s scores: judge features, the label maps of every
    ``scene_frame_stride``-th frame (the frames :func:`~world_model.eval.scene_iou.scene_iou` reads)
    and ``segmenter``'s classes of the FRONT view at those frames."""
    cameras = np.asarray(clip.cameras)
    features = getattr(judge, "frame_features", None)
    t, v, h, w = cameras.shape[:4]
    labels = np.zeros((t, v, h, w), np.uint8)
    read = _scene_frames(clip, config)
    labels[read] = scene_labels([clip.frames[i] for i in read], h, w)
    front, front_classes = front_view_index(clip.frames[0].rig.names), None
    if segmenter is not None and front is not None:
        front_classes = np.zeros((t, h, w), np.uint8)
        front_classes[read] = segmenter.predict(cameras[read, front])
    return ClipTruth(features(cameras) if features else None, labels, front_classes)


@dataclass(frozen=True, eq=False)
class ClipScores:
    """Everything measured on one row's frames of one clip, before pooling over clips."""

    clip: str
    fps: float
    psnr_per_frame: np.ndarray  # (T,) mean over views, capped at ReportConfig.psnr_cap_db
    ssim_scored: np.ndarray  # (ceil(T / frame_stride),) mean over views, every frame_stride-th frame
    lidar_mae_per_frame: np.ndarray | None  # (T,) range MAE m; None for rows without LiDAR
    chamfers: tuple[float, ...]  # every lidar_stride-th frame
    object_psnrs: tuple[float, ...]  # see object_scores
    object_maes: tuple[float, ...]
    road_maes: tuple[float, ...]  # see object_scores
    motion: SensorPairs[ChangeSums]  # lagged_change over motion_lag_s
    jumps: SensorPairs[JumpSums] | None  # chunk_jumps at the pass starts; None: not generated in passes
    answers: tuple[Answer, ...]
    features: np.ndarray | None  # (T, D) judge frame features of the generated frames; None without them
    long_horizon: LongHorizon | None  # clips of at least twice long_window_s
    scene_iou: SceneIoU | None  # clips of at least a second (the scene IoU pools whole seconds)
    decisions: ClipDecisions | None = None  # what a policy reads (clip_decisions)


def score_clip(
    gen: Generated,
    clip: Clip,
    judge: JudgeBackend,
    segmenter: Segmenter,
    truth: ClipTruth,
    config: ReportConfig,
    sim: ProceduralSimulator | None = None,
) -> ClipScores:
    """Score ``gen``, a row's sensors for ``clip``, against ``truth`` (:func:`clip_truth`);
    ``segmenter`` labels the row's camera pixels for the scene IoU."""
    sim = sim or ProceduralSimulator()
    crop_config = judge.crop_config if isinstance(judge, CnnJudge) else CropConfig()
    answers = judge_clip(judge, clip, gen.cameras, sim, config, crop_config)
    gt = np.asarray(clip.cameras)
    # Frame by frame: a 600-frame clip in float64 at once would take gigabytes.
    per_frame = np.array([psnr(gen.cameras[t], gt[t]).mean() for t in range(clip.num_frames)])
    per_frame = np.minimum(per_frame, config.psnr_cap_db)
    scored = slice(None, None, config.frame_stride)
    features = getattr(judge, "frame_features", None)
    gen_features = features(gen.cameras) if features else None
    lidar_mae, chamfers = None, ()
    if gen.lidar is not None:
        spec = clip.frames[0].lidar
        lidar_mae = np.array([lidar_range_mae(_ranges(gen.lidar, i), _ranges(clip.lidar, i), spec)
                              for i in range(clip.num_frames)])  # fmt: skip
        chamfers = tuple(chamfer_distance(_ranges(gen.lidar, i), _ranges(clip.lidar, i), spec,
                                          max_points=config.chamfer_max_points)
                         for i in range(0, clip.num_frames, config.lidar_stride))  # fmt: skip
    object_psnrs, object_maes, road_maes = object_scores(gen, clip, sim, config)
    scene = None
    if clip.num_frames >= round(clip.fps):
        scene = scene_iou(gen.cameras, truth.scene_labels, clip.fps, segmenter, config.long_window_s,
                          config.scene_frame_stride)  # fmt: skip
    decisions = clip_decisions(gen, clip, segmenter, truth, config)
    motion = motion_sums(gen, clip, config)
    long = None
    if clip.num_frames / clip.fps >= 2 * config.long_window_s:
        long = long_horizon(clip, per_frame, lidar_mae, gen_features, truth.features, motion, config)
    return ClipScores(
        clip=clip.name,
        fps=clip.fps,
        psnr_per_frame=per_frame,
        ssim_scored=ssim(gen.cameras[scored], gt[scored]).mean(axis=1),
        lidar_mae_per_frame=lidar_mae,
        chamfers=chamfers,
        object_psnrs=tuple(object_psnrs),
        object_maes=tuple(object_maes),
        road_maes=tuple(road_maes),
        motion=motion,
        jumps=pass_jumps(gen, clip) if gen.pass_starts else None,
        answers=tuple(answers),
        features=gen_features,
        long_horizon=long,
        scene_iou=scene,
        decisions=decisions,
    )


def clip_decisions(
    gen: Generated, clip: Clip, segmenter: Segmenter, truth: ClipTruth, config: ReportConfig
) -> ClipDecisions:
    """What a policy reads on one clip (:mod:`world_model.eval.decisions`), the row's sensors against
    the recording's: the LiDAR's nearest object per sector on every frame (rows with LiDAR), the lead
    vehicle and the lane markings in FRONT on the frames the scene IoU reads, ``segmenter`` labelling
    the row's view as it labelled the recording's (``truth.front_classes``)."""
    per_frame = [DecisionSums() for _ in range(clip.num_frames)]
    if gen.lidar is not None:
        for f, frame in enumerate(clip.frames):
            per_frame[f] = lidar_decisions(_ranges(clip.lidar, f), _ranges(gen.lidar, f), frame.lidar)
    front = front_view_index(clip.frames[0].rig.names)
    if front is not None and truth.front_classes is not None:
        read = _scene_frames(clip, config)
        predicted = segmenter.predict(np.asarray(gen.cameras[read, front]))
        for f, classes in zip(read, predicted, strict=True):
            frame = clip.frames[f]
            camera = frame.rig.cameras[front]
            per_frame[f] += camera_decisions(truth.front_classes[f], classes, camera, frame.lidar.mount_height)
    step = max(1, round(clip.fps))
    seconds = tuple(sum(per_frame[s * step : (s + 1) * step], DecisionSums()) for s in range(clip.num_frames // step))
    return ClipDecisions(sum(per_frame, DecisionSums()), seconds)


def _scene_frames(clip: Clip, config: ReportConfig) -> list[int]:
    """The frames the scene IoU and the FRONT readings read: every ``scene_frame_stride``-th."""
    return list(range(0, clip.num_frames, config.scene_frame_stride))


def object_scores(
    gen: Generated, clip: Clip, sim: ProceduralSimulator, config: ReportConfig
) -> tuple[list[float], list[float], list[float]]:
    """Does the row keep the recording's objects? Per scored frame of one clip: the PSNR over the
    pixels where the recording's objects are visible (every ``frame_stride``-th frame with one in
    view), the range MAE over its object returns and, apart, over its other returns (the road and
    the ground; every ``lidar_stride``-th frame). A row that paints road where the vehicles were
    scores low on the object scores though the whole frame barely changes (objects cover ~3 % of
    the pixels and ~4 % of the rays); one that loses the road plane, on the road MAE."""
    psnrs: list[float] = []
    maes: list[float] = []
    road_maes: list[float] = []
    cams = np.asarray(clip.cameras)
    for f in range(clip.num_frames):
        on_cams, on_lidar = f % config.frame_stride == 0, gen.lidar is not None and f % config.lidar_stride == 0
        if not (on_cams or on_lidar):
            continue
        cam_mask, lidar_mask = sim.object_masks(clip.frames[f])
        if on_cams and (p := masked_psnr(gen.cameras[f], cams[f], cam_mask)) is not None:
            psnrs.append(min(p, config.psnr_cap_db))
        if on_lidar:
            errors = lidar_region_errors(
                _ranges(gen.lidar, f), _ranges(clip.lidar, f), lidar_mask, clip.frames[f].lidar
            )
            maes += [] if errors.objects_m is None else [errors.objects_m]
            road_maes += [] if errors.road_m is None else [errors.road_m]
    return psnrs, maes, road_maes


def per_sensor(gen: Generated, clip: Clip, total: Callable[[np.ndarray], S]) -> SensorPairs[S]:
    """``total`` of the row's stream and of the recording's, per sensor the row generates."""
    streams = {"cameras": (gen.cameras, clip.cameras)}
    if gen.lidar is not None:
        streams["lidar"] = (gen.lidar, clip.lidar)
    return {
        sensor: StreamPair(total(generated), total(np.asarray(recorded)))
        for sensor, (generated, recorded) in streams.items()
    }


def motion_sums(gen: Generated, clip: Clip, config: ReportConfig) -> SensorPairs[ChangeSums]:
    """One clip's :func:`metrics.lagged_change` sums over ``motion_lag_s``, per sensor."""
    lag = max(1, round(config.motion_lag_s * clip.fps))
    return per_sensor(gen, clip, lambda frames: lagged_change(frames, lag))


def pass_jumps(gen: Generated, clip: Clip) -> SensorPairs[JumpSums]:
    """One clip's frame-to-frame changes at and between ``gen``'s pass starts, per sensor."""
    starts = gen.pass_starts or ()
    return per_sensor(gen, clip, lambda frames: chunk_jumps(frames, starts))


def motion_scores(sums: SensorPairs[ChangeSums]) -> dict[str, float | None]:
    """Table 1's motion scores: per sensor, how much the row's frames change over ``motion_lag_s``
    relative to the recording at the same frames (:func:`metrics.motion_ratio`, one clip's sums or
    pooled over clips). 1 = moves as much as the recording; near 0 = stuck on its first frames,
    which the error scores cannot tell from a stable rollout on a straight road (see
    :func:`rows.first_frame_row`); above 1 = more change than the recording (drift or flicker).
    The recordings' LiDAR changes only where objects move or the road bends, so ``motion_lidar``
    mostly measures how far a row's LiDAR wanders."""
    out: dict[str, float | None] = {"motion_cameras": None, "motion_lidar": None}
    for sensor, pair in sums.items():
        out[f"motion_{sensor}"] = motion_ratio(pair.generated, pair.recording)
    return out


def chunk_jump_scores(jumps: SensorPairs[JumpSums]) -> dict[str, float | None]:
    """Table 1's inter-chunk consistency: per sensor, how much more the stream changes into the
    first frame of a generation pass than between frames of one pass (:func:`metrics.chunk_jumps`),
    relative to the recording at the same frames. 1 = pass boundaries as smooth as the recording's
    motion; above 1 = a visible jump (flicker) at every chunk boundary. None without passes. For
    the student the first boundary is the switch from the reference model's first frame to the
    first causal chunk; it weighs the same in rows with and without context refresh."""
    out: dict[str, float | None] = {"chunk_jump_cameras": None, "chunk_jump_lidar": None}
    for sensor, pair in jumps.items():
        gen, rec = pair.generated.ratio(), pair.recording.ratio()
        out[f"chunk_jump_{sensor}"] = gen / rec if gen is not None and rec else None
    return out


def long_horizon(
    clip: Clip,
    psnr_per_frame: np.ndarray,
    lidar_mae_per_frame: np.ndarray | None,
    gen_features: np.ndarray | None,
    gt_features: np.ndarray | None,
    motion: SensorPairs[ChangeSums],
    config: ReportConfig,
) -> LongHorizon:
    """Stability of a long rollout: per-second PSNR (and LiDAR MAE) curves, and the last
    ``long_window_s`` seconds against the first — PSNR ratio (1 = no degradation, < 1 worse) and
    the frame Fréchet distance of each window to the ground truth's same window (ratio > 1 worse)."""
    curve = per_second_curve(psnr_per_frame, clip.fps)
    frechet = None
    if gen_features is not None and gt_features is not None:
        w = round(config.long_window_s * clip.fps)
        first = frechet_features(gen_features[:w], gt_features[:w])
        last = frechet_features(gen_features[-w:], gt_features[-w:])
        frechet = WindowFrechet(first, last, last / first if first > 0 else None)
    lidar = None if lidar_mae_per_frame is None else per_second_curve(lidar_mae_per_frame, clip.fps)
    moved = motion_scores(motion)
    return LongHorizon(
        clip=clip.name,
        seconds=len(curve),
        psnr_per_second=tuple(curve.tolist()),
        ratio_last_first=long_horizon_ratio(curve, config.long_window_s),
        frechet=frechet,
        lidar_mae_per_second=None if lidar is None else tuple(lidar.tolist()),
        motion_cameras=moved["motion_cameras"],
        motion_lidar=moved["motion_lidar"],
    )


def _ranges(lidar: np.ndarray, frame: int) -> np.ndarray:
    return np.asarray(lidar[frame], np.float32)
