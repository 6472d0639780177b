"""How the report samples each clip: strides, windows and caps (every default visible)."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class ReportConfig:
    """Sampling of the evaluation. Part of every cached row's key (:mod:`~world_model.eval.report.cache`)."""

    frame_stride: int = 5  # judge questions, PSNR/SSIM and frame Fréchet on every k-th frame
    clip_window: int = 8  # frames per window of the clip Fréchet distance
    lidar_stride: int = 10  # LiDAR MAE / Chamfer on every k-th frame
    chamfer_max_points: int = 8192
    psnr_cap_db: float = 100.0  # identical frames (PSNR inf) count as this when averaged
    long_window_s: int = 10  # long-horizon ratio: last vs first window, seconds
    motion_lag_s: float = 1.0  # motion scores: change between frames this far apart, seconds
    scene_frame_stride: int = 5  # scene IoU: the segmenter labels every k-th frame

    def __post_init__(self) -> None:
        for name in ("frame_stride", "lidar_stride", "chamfer_max_points", "long_window_s", "scene_frame_stride"):
            if getattr(self, name) < 1:
                raise ValueError(f"ReportConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.clip_window < 2:  # a window's features include the change between its frames
            raise ValueError(f"ReportConfig.clip_window must be >= 2 frames, got {self.clip_window}")
        if self.motion_lag_s <= 0:
            raise ValueError(f"ReportConfig.motion_lag_s must be > 0 seconds, got {self.motion_lag_s}")

    def to_json(self) -> dict[str, float]:
        return asdict(self)
