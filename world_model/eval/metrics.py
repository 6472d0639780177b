"""Quality metrics of generated sensors against the ground truth at equal controls (§9).

* Images: PSNR and SSIM (Gaussian-window SSIM of Wang et al. 2004 on luma).
* Distributions: the Fréchet distance between Gaussians fitted to *judge* features of frames
  (:func:`frechet_judge_frame`, "FID-like") and of short clip windows (:func:`frechet_judge_clip`,
  "FVD-like"). These use our small judge networks' features, not Inception / I3D: the numbers are
  comparable between rows of one report, never with published FID/FVD.
* Segmentation: per-class pixel counts summed over frames (:class:`ConfusionSums`), their IoU and
  accuracy (the scene IoU of :mod:`world_model.eval.scene_iou`).
* LiDAR: range MAE on ground-truth returns (also split into road and object returns,
  :func:`lidar_region_errors`) and the Chamfer distance of back-projected points.
* Long horizon: any per-frame metric averaged per second of a rollout, and the ratio of its last
  10 s to its first 10 s (:func:`long_horizon_ratio`).
* Inter-chunk consistency: how much more a stream changes where a new generation pass begins (a
  causal chunk, a teacher window) than between frames of one pass (:func:`chunk_jumps`), the
  flickering that latent context refresh is meant to reduce (§4.2).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from world_model.sensors import LidarSpec


@dataclass(frozen=True)
class SsimConfig:
    """Constants of SSIM (Wang et al. 2004): Gaussian window and stabilizers."""

    sigma: float = 1.5
    window: int = 11
    k1: float = 0.01
    k2: float = 0.03
    data_range: float = 255.0


def _check_pair(a: np.ndarray, b: np.ndarray, what: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{what}: generated and ground truth must have the same shape, got {a.shape} vs {b.shape}")


def psnr(generated: np.ndarray, target: np.ndarray, data_range: float = 255.0) -> np.ndarray:
    """PSNR in dB of each image: arrays (..., H, W, C) -> (...). ``inf`` where they are identical."""
    _check_pair(generated, target, "psnr")
    if generated.ndim < 3:
        raise ValueError(f"psnr expects (..., H, W, C) images, got shape {generated.shape}")
    diff = generated.astype(np.float64) - target.astype(np.float64)
    mse = np.mean(diff * diff, axis=(-3, -2, -1))
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(data_range**2 / mse)


def masked_psnr(generated: np.ndarray, target: np.ndarray, mask: np.ndarray, data_range: float = 255.0) -> float | None:
    """PSNR in dB over the pixels where ``mask`` (..., H, W) is True, pooled across images
    (..., H, W, C); None when the mask is empty, ``inf`` where those pixels are identical."""
    _check_pair(generated, target, "masked_psnr")
    if mask.shape != generated.shape[:-1]:
        raise ValueError(f"mask must be {generated.shape[:-1]} (the images without channels), got {mask.shape}")
    if not mask.any():
        return None
    diff = generated[mask].astype(np.float64) - target[mask].astype(np.float64)
    mse = float(np.mean(diff * diff))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(data_range**2 / mse))


def _luma(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB -> (H, W) float64 luma (ITU-R BT.601 weights)."""
    return img.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def ssim(generated: np.ndarray, target: np.ndarray, config: SsimConfig = SsimConfig()) -> np.ndarray:
    """Mean SSIM of each image pair on luma: (..., H, W, 3) -> (...). 1 for identical images."""
    _check_pair(generated, target, "ssim")
    if generated.ndim < 3 or generated.shape[-1] != 3:
        raise ValueError(f"ssim expects (..., H, W, 3) RGB images, got shape {generated.shape}")
    lead = generated.shape[:-3]
    g = generated.reshape(-1, *generated.shape[-3:])
    t = target.reshape(-1, *target.shape[-3:])
    c1, c2 = (config.k1 * config.data_range) ** 2, (config.k2 * config.data_range) ** 2
    ksize = (config.window, config.window)

    def blur(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x, ksize, config.sigma, borderType=cv2.BORDER_REFLECT)

    out = np.empty(len(g))
    for i in range(len(g)):
        x, y = _luma(g[i]), _luma(t[i])
        mx, my = blur(x), blur(y)
        sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        num = (2 * mx * my + c1) * (2 * sxy + c2)
        den = (mx * mx + my * my + c1) * (sxx + syy + c2)
        out[i] = float(np.mean(num / den))
    return out.reshape(lead)


# ----------------------------------------------------------------------------- Fréchet distances


def gaussian_stats(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D, D) of features (N, D), N >= 2."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 2:
        raise ValueError(f"need features of shape (N >= 2, D) to fit a Gaussian, got {f.shape}")
    return f.mean(axis=0), np.cov(f, rowvar=False).reshape(f.shape[1], f.shape[1])


def _sqrtm_psd(m: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh((m + m.T) / 2)
    return (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T


def frechet_distance(mu1: np.ndarray, cov1: np.ndarray, mu2: np.ndarray, cov2: np.ndarray) -> float:
    """Fréchet (2-Wasserstein) distance between N(mu1, cov1) and N(mu2, cov2):
    ``|mu1 - mu2|^2 + tr(cov1 + cov2 - 2 (cov1^1/2 cov2 cov1^1/2)^1/2)``.

    The matrix square root goes through symmetric eigendecompositions (both covariances are PSD),
    so no complex parts and no scipy are needed.
    """
    if mu1.shape != mu2.shape or cov1.shape != cov2.shape or cov1.shape != (len(mu1), len(mu1)):
        raise ValueError(f"mismatched Gaussian shapes: {mu1.shape}, {cov1.shape} vs {mu2.shape}, {cov2.shape}")
    s1 = _sqrtm_psd(cov1)
    cross = np.linalg.eigvalsh((s1 @ cov2 @ s1 + (s1 @ cov2 @ s1).T) / 2)
    tr_sqrt = float(np.sum(np.sqrt(np.clip(cross, 0.0, None))))
    d = float(np.sum((mu1 - mu2) ** 2) + np.trace(cov1) + np.trace(cov2) - 2.0 * tr_sqrt)
    return max(d, 0.0)


def frechet_features(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to two feature sets (N, D) and (M, D)."""
    return frechet_distance(*gaussian_stats(a), *gaussian_stats(b))


FrameFeatures = Callable[[np.ndarray], np.ndarray]  # (N, V, H, W, 3) uint8 -> (N, D) float


def clip_window_features(frame_features: np.ndarray, window: int) -> np.ndarray:
    """Features of consecutive, non-overlapping windows of a clip: (T, D) -> (T // window, 2 D).

    Each window is described by the mean of its frame features and the mean absolute change between
    consecutive frames, so that a clip of good frames that flicker or freeze still differs.
    """
    if window < 2:
        raise ValueError(f"clip windows need at least 2 frames, got window={window}")
    n = frame_features.shape[0] // window
    f = np.asarray(frame_features, dtype=np.float64)[: n * window].reshape(n, window, -1)
    return np.concatenate([f.mean(axis=1), np.abs(np.diff(f, axis=1)).mean(axis=1)], axis=1)


def frechet_judge_frame(generated: np.ndarray, target: np.ndarray, features: FrameFeatures) -> float:
    """ "FID-like": Fréchet distance of judge frame features. Frames (N, V, H, W, 3) uint8 each."""
    return frechet_features(features(generated), features(target))


def frechet_judge_clip(
    generated: list[np.ndarray], target: list[np.ndarray], features: FrameFeatures, window: int = 8
) -> float:
    """ "FVD-like": Fréchet distance of judge features of ``window``-frame clip windows.

    ``generated`` / ``target``: lists of clips, each (T, V, H, W, 3) uint8.
    """
    gen = np.concatenate([clip_window_features(features(c), window) for c in generated])
    tgt = np.concatenate([clip_window_features(features(c), window) for c in target])
    return frechet_features(gen, tgt)


# ---------------------------------------------------------------------------------- segmentation


@dataclass(frozen=True)
class ConfusionSums:
    """Per-class pixel counts of a segmentation against its labels, summed over frames (so that a
    class's IoU weighs every pixel of the set alike, not every frame). Adding two sums pools them."""

    intersection: np.ndarray  # (C,) int64: pixels predicted c where the label is c
    predicted: np.ndarray  # (C,) int64: pixels predicted c
    labelled: np.ndarray  # (C,) int64: pixels labelled c

    @classmethod
    def zeros(cls, num_classes: int) -> ConfusionSums:
        return cls(*(np.zeros(num_classes, dtype=np.int64) for _ in range(3)))

    def __add__(self, other: ConfusionSums) -> ConfusionSums:
        if len(self.labelled) != len(other.labelled):
            raise ValueError(f"cannot pool sums of {len(self.labelled)} and {len(other.labelled)} classes")
        return ConfusionSums(
            self.intersection + other.intersection, self.predicted + other.predicted, self.labelled + other.labelled
        )

    def iou(self) -> list[float | None]:
        """Per class: intersection over union; None where neither side has the class."""
        union = self.predicted + self.labelled - self.intersection
        return [float(i / u) if u > 0 else None for i, u in zip(self.intersection, union, strict=True)]

    def accuracy(self) -> list[float | None]:
        """Per class: the fraction of its labelled pixels predicted right (None: never labelled)."""
        return [float(i / n) if n > 0 else None for i, n in zip(self.intersection, self.labelled, strict=True)]


def confusion_sums(predicted: np.ndarray, labels: np.ndarray, num_classes: int) -> ConfusionSums:
    """Per-class counts of integer class maps ``predicted`` vs ``labels`` (same shape, values in
    ``[0, num_classes)``)."""
    _check_pair(predicted, labels, "confusion_sums")
    p, t = np.asarray(predicted).ravel(), np.asarray(labels).ravel()
    for name, a in (("predicted", p), ("labels", t)):
        if a.size and (a.min() < 0 or a.max() >= num_classes):
            raise ValueError(f"confusion_sums: {name} holds classes outside [0, {num_classes}): {a.min()}..{a.max()}")
    return ConfusionSums(
        intersection=np.bincount(t[p == t], minlength=num_classes).astype(np.int64),
        predicted=np.bincount(p, minlength=num_classes).astype(np.int64),
        labelled=np.bincount(t, minlength=num_classes).astype(np.int64),
    )


# ----------------------------------------------------------------------------------------- LiDAR


def lidar_range_mae(generated: np.ndarray, target: np.ndarray, spec: LidarSpec | None = None) -> float:
    """Mean absolute range error (m) over the ground truth's returns (rays with no return are
    skipped; a generated no-return on a true return counts its full range as error)."""
    _check_pair(generated, target, "lidar_range_mae")
    spec = spec or LidarSpec()
    g, t = np.asarray(generated, dtype=np.float64), np.asarray(target, dtype=np.float64)
    hit = t != spec.no_return
    if not hit.any():
        raise ValueError("the ground truth has no LiDAR returns: range MAE is undefined")
    return float(np.mean(np.abs(g[hit] - t[hit])))


def masked_range_mae(generated: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float | None:
    """Mean absolute range error (m) over the rays where ``mask`` (beams, azimuth) is True, e.g. the
    ground truth's object returns; None when the mask is empty."""
    _check_pair(generated, target, "masked_range_mae")
    if mask.shape != generated.shape:
        raise ValueError(f"mask must be {generated.shape} (the range map), got {mask.shape}")
    if not mask.any():
        return None
    g, t = np.asarray(generated, dtype=np.float64), np.asarray(target, dtype=np.float64)
    return float(np.mean(np.abs(g[mask] - t[mask])))


@dataclass(frozen=True)
class LidarRegionErrors:
    """Range MAE (m) of one frame split by what the ground truth's ray hit; None where it hit none."""

    road_m: float | None  # returns outside every object: the road and the ground around it
    objects_m: float | None  # returns on the objects


def lidar_region_errors(
    generated: np.ndarray, target: np.ndarray, object_returns: np.ndarray, spec: LidarSpec | None = None
) -> LidarRegionErrors:
    """Range MAE over the ground truth's object returns and, separately, over its other returns, of
    range maps (beams, azimuth). ``object_returns`` (beams, azimuth) bool marks the rays that hit an
    object (``ProceduralSimulator.object_masks``). A row that keeps the vehicles but loses the road
    plane scores badly on ``road_m`` only; one that paints road over the vehicles, on ``objects_m``."""
    _check_pair(generated, target, "lidar_region_errors")
    if object_returns.shape != target.shape or object_returns.dtype != bool:
        got = f"{object_returns.dtype} {object_returns.shape}"
        raise ValueError(f"object_returns must be bool {target.shape} (the range map), got {got}")
    spec = spec or LidarSpec()
    road = ~object_returns & (np.asarray(target) != spec.no_return)
    return LidarRegionErrors(
        road_m=masked_range_mae(generated, target, road),
        objects_m=masked_range_mae(generated, target, object_returns),
    )


def lidar_points(ranges: np.ndarray, spec: LidarSpec | None = None) -> np.ndarray:
    """Back-project a range map (beams, azimuth) to LiDAR-frame points (N, 3) of its returns."""
    spec = spec or LidarSpec()
    r = np.asarray(ranges, dtype=np.float64)
    if r.shape != (spec.beams, spec.azimuth):
        raise ValueError(f"range map must be {(spec.beams, spec.azimuth)} for this LidarSpec, got {r.shape}")
    hit = (r != spec.no_return) & (r > 0)
    return spec.ray_directions()[hit] * r[hit][:, None]


def chamfer_distance(
    generated: np.ndarray,
    target: np.ndarray,
    spec: LidarSpec | None = None,
    max_points: int | None = None,
) -> float:
    """Symmetric Chamfer distance (m): mean nearest-neighbour distance from each generated point to
    the ground truth plus the reverse, on back-projected returns of two range maps.

    ``max_points`` keeps every k-th point of each cloud (deterministic) to bound the cost. Exact
    nearest neighbours from a k-d tree (identical clouds give exactly 0)."""
    a, b = lidar_points(generated, spec), lidar_points(target, spec)
    if max_points is not None:
        a, b = a[:: max(1, -(-len(a) // max_points))], b[:: max(1, -(-len(b) // max_points))]
    if len(a) == 0 and len(b) == 0:
        return 0.0
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    a_to_b = cKDTree(b).query(a)[0]
    b_to_a = cKDTree(a).query(b)[0]
    return float(a_to_b.mean() + b_to_a.mean())


# ------------------------------------------------------------------------ inter-chunk consistency


@dataclass
class JumpSums:
    """Summed frame-to-frame changes of a stream, split at the starts of its generation passes.
    Sums (not means) so that clips of different lengths pool by adding."""

    boundary: float = 0.0  # change into a frame that starts a new pass
    boundary_count: int = 0
    within: float = 0.0  # change between consecutive frames of one pass
    within_count: int = 0

    def __add__(self, other: JumpSums) -> JumpSums:
        return JumpSums(
            self.boundary + other.boundary,
            self.boundary_count + other.boundary_count,
            self.within + other.within,
            self.within_count + other.within_count,
        )

    def ratio(self) -> float | None:
        """Mean change at pass starts over mean change inside passes. None when a side is empty or
        the stream never changes inside a pass (a stream frozen within its passes is better read
        from its PSNR curves than from an infinite ratio)."""
        if not self.boundary_count or not self.within_count or self.within == 0:
            return None
        return (self.boundary / self.boundary_count) / (self.within / self.within_count)


def chunk_jumps(frames: np.ndarray, starts: Sequence[int]) -> JumpSums:
    """Frame-to-frame changes of ``frames`` (T, ...): the mean absolute difference between frame t
    and t - 1, for every t >= 1, summed separately over the ``starts`` (frames that begin a new
    generation pass) and over the other frames. Frame 0 has no predecessor and is ignored. On LiDAR
    range maps a ray switching between a return and no return counts its whole range: such
    dropouts at a chunk boundary are flicker too."""
    t = len(frames)
    first = sorted({int(s) for s in starts})
    if any(not 1 <= s < t for s in first):
        raise ValueError(f"pass starts must be frames 1..{t - 1}, got {list(starts)}")
    change = np.array([np.abs(frames[i].astype(np.float64) - frames[i - 1]).mean() for i in range(1, t)])
    at_start = np.zeros(t - 1, dtype=bool)
    at_start[[s - 1 for s in first]] = True
    return JumpSums(
        float(change[at_start].sum()), int(at_start.sum()), float(change[~at_start].sum()), int((~at_start).sum())
    )


@dataclass
class ChangeSums:
    """Summed changes between frames a fixed lag apart (:func:`lagged_change`); sums, so clips pool
    by adding."""

    total: float = 0.0
    pairs: int = 0

    def __add__(self, other: ChangeSums) -> ChangeSums:
        return ChangeSums(self.total + other.total, self.pairs + other.pairs)

    def mean(self) -> float | None:
        return self.total / self.pairs if self.pairs else None


def lagged_change(frames: np.ndarray, lag: int) -> ChangeSums:
    """How much a stream moves: the mean absolute difference between frame t and frame t - ``lag``
    of ``frames`` (T, ...), summed over t >= ``lag``. A stream stuck on one frame sums to 0."""
    if lag < 1:
        raise ValueError(f"lag must be >= 1 frame, got {lag}")
    pairs = range(lag, len(frames))
    return ChangeSums(
        float(sum(np.abs(frames[t].astype(np.float64) - frames[t - lag]).mean() for t in pairs)), len(pairs)
    )


def motion_ratio(generated: ChangeSums, recording: ChangeSums) -> float | None:
    """Mean lagged change of a generated stream over the recording's: 1 = it moves as much as the
    recording, 0 = frozen, above 1 = more change (drift, flicker). None without pairs or when the
    recording never changes."""
    gen, rec = generated.mean(), recording.mean()
    return None if gen is None or not rec else gen / rec


# ---------------------------------------------------------------------------------- long horizon


def per_second_curve(per_frame: np.ndarray, fps: float) -> np.ndarray:
    """Average a per-frame metric (T,) over whole seconds -> (T // fps,); a partial last second is
    dropped. Infinite values (PSNR of identical frames) are capped by the caller if needed."""
    step = round(fps)
    if step < 1 or abs(step - fps) > 1e-6:
        raise ValueError(f"fps must be a positive integer rate, got {fps}")
    v = np.asarray(per_frame, dtype=np.float64)
    n = len(v) // step
    if n == 0:
        raise ValueError(f"need at least one second ({step} frames), got {len(v)}")
    return v[: n * step].reshape(n, step).mean(axis=1)


def long_horizon_ratio(curve: np.ndarray, window_s: int = 10) -> float:
    """Mean of the last ``window_s`` seconds of a per-second curve over the mean of the first."""
    c = np.asarray(curve, dtype=np.float64)
    if len(c) < window_s:
        raise ValueError(f"the curve covers {len(c)} s; need at least window_s={window_s}")
    first, last = c[:window_s].mean(), c[-window_s:].mean()
    if first == 0:
        raise ValueError("the first window's mean is 0: the ratio is undefined")
    return float(last / first)
