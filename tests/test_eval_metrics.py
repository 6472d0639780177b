"""Quality metrics against known values (world_model.eval.metrics)."""

import math

import numpy as np
import pytest

from world_model.eval.metrics import (
    JumpSums,
    chamfer_distance,
    chunk_jumps,
    clip_window_features,
    frechet_distance,
    frechet_features,
    frechet_judge_clip,
    frechet_judge_frame,
    lidar_points,
    lidar_range_mae,
    long_horizon_ratio,
    per_second_curve,
    psnr,
    ssim,
)
from world_model.sensors import LidarSpec


def _images(seed: int = 0, shape=(2, 32, 48, 3)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(40, 216, size=shape).astype(np.float32)
    return np.clip(base, 0, 255).astype(np.uint8)


def test_identical_images_give_psnr_inf_and_ssim_one():
    x = _images()
    assert np.all(np.isinf(psnr(x, x)))
    np.testing.assert_allclose(ssim(x, x), 1.0, atol=1e-12)


def test_psnr_of_known_noise_variance():
    x = np.full((1, 64, 64, 3), 128, dtype=np.uint8)
    rng = np.random.default_rng(1)
    sign = rng.choice([-1, 1], size=x.shape)
    y = (x.astype(int) + 10 * sign).astype(np.uint8)  # MSE exactly 100
    assert psnr(y, x)[0] == pytest.approx(10 * math.log10(255**2 / 100), abs=1e-9)


def test_ssim_drops_with_noise_and_shift():
    x = _images(2, (1, 64, 96, 3))
    noisy = np.clip(x.astype(int) + np.random.default_rng(3).normal(0, 30, x.shape), 0, 255).astype(np.uint8)
    shifted = np.roll(x, 3, axis=2)
    s_noisy, s_shift = ssim(noisy, x)[0], ssim(shifted, x)[0]
    assert s_noisy < 0.9 and s_shift < 0.9
    assert psnr(noisy, x)[0] < 25


def test_frechet_of_gaussians_matches_closed_form():
    mu1, mu2 = np.array([0.0, 1.0]), np.array([2.0, -1.0])
    c1, c2 = np.diag([1.0, 4.0]), np.diag([9.0, 1.0])
    # Commuting (diagonal) covariances: tr term = sum (sqrt(a) - sqrt(b))^2.
    expected = 8.0 + (1 - 3) ** 2 + (2 - 1) ** 2
    assert frechet_distance(mu1, c1, mu2, c2) == pytest.approx(expected, abs=1e-9)
    assert frechet_distance(mu1, c1, mu1, c1) == pytest.approx(0.0, abs=1e-9)


def test_frechet_of_samples_converges_to_closed_form():
    rng = np.random.default_rng(4)
    a = rng.normal([0, 0, 0], [1, 2, 3], size=(20000, 3))
    b = rng.normal([1, 0, 0], [1, 2, 1], size=(20000, 3))
    assert frechet_features(a, b) == pytest.approx(1.0 + (3 - 1) ** 2, rel=0.05)
    assert frechet_features(a, a) == pytest.approx(0.0, abs=1e-9)


def test_frechet_judge_frame_and_clip_with_a_feature_function():
    feats = lambda frames: frames.reshape(len(frames), -1)[:, :4].astype(np.float64)  # noqa: E731
    clips = [_images(s, (16, 2, 4, 4, 3)) for s in range(4)]
    frames = np.concatenate(clips)
    assert frechet_judge_frame(frames, frames, feats) == pytest.approx(0.0, abs=1e-9)
    assert frechet_judge_clip(clips, clips, feats, window=4) == pytest.approx(0.0, abs=1e-9)
    brighter = [np.clip(c.astype(int) + 40, 0, 255).astype(np.uint8) for c in clips]
    assert frechet_judge_clip(brighter, clips, feats, window=4) > 100


def test_clip_window_features_see_flicker():
    steady = np.ones((8, 3))
    flicker = np.tile([[0.0] * 3, [2.0] * 3], (4, 1))
    a, b = clip_window_features(steady, 4), clip_window_features(flicker, 4)
    np.testing.assert_allclose(a[:, :3], b[:, :3])  # same mean
    assert np.all(b[:, 3:] > a[:, 3:])  # but the change term differs


def test_lidar_metrics_identity_and_known_offset():
    spec = LidarSpec(beams=4, azimuth=64)
    r = np.full((4, 64), 20.0, dtype=np.float32)
    r[0] = spec.no_return
    assert lidar_range_mae(r, r, spec) == 0.0
    assert chamfer_distance(r, r, spec) == 0.0
    assert lidar_range_mae(r + 1.5, r, spec) == pytest.approx(1.5)
    far = np.where(r > 0, 21.0, spec.no_return).astype(np.float32)
    # Each point moves 1 m radially; nearest neighbours are the corresponding points.
    assert chamfer_distance(far, r, spec) == pytest.approx(2.0, abs=1e-6)
    pts = lidar_points(r, spec)
    assert pts.shape == (3 * 64, 3)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 20.0)


def test_lidar_bad_input_is_specific():
    spec = LidarSpec(beams=4, azimuth=64)
    with pytest.raises(ValueError, match="no LiDAR returns"):
        lidar_range_mae(np.zeros((4, 64)), np.zeros((4, 64)), spec)
    with pytest.raises(ValueError, match="same shape"):
        lidar_range_mae(np.zeros((4, 64)), np.zeros((4, 32)), spec)


def test_per_second_curve_and_long_horizon_ratio():
    fps = 10
    per_frame = np.repeat(np.linspace(30, 15, 60), fps)  # 60 s, falling quality
    curve = per_second_curve(np.r_[per_frame, [99.0] * 3], fps)  # partial last second dropped
    assert curve.shape == (60,)
    np.testing.assert_allclose(curve, np.linspace(30, 15, 60))
    assert long_horizon_ratio(curve, 10) == pytest.approx(curve[-10:].mean() / curve[:10].mean())
    assert long_horizon_ratio(np.ones(60)) == 1.0
    with pytest.raises(ValueError, match="at least window_s"):
        long_horizon_ratio(np.ones(5), 10)


def test_chunk_jumps_split_changes_at_pass_starts():
    # Steady motion of 1 per frame, plus a jump of 4 into frames 3 and 6 (where new passes start).
    frames = np.arange(8, dtype=np.float64)[:, None, None] + np.zeros((8, 2, 3))
    frames[3:] += 4
    frames[6:] += 4
    sums = chunk_jumps(frames, [3, 6])
    assert (sums.boundary, sums.boundary_count, sums.within, sums.within_count) == (10.0, 2, 5.0, 5)
    assert sums.ratio() == pytest.approx(5.0)
    assert chunk_jumps(np.arange(8.0)[:, None], [3, 6]).ratio() == pytest.approx(1.0)  # no jumps
    pooled = sums + chunk_jumps(np.arange(4.0)[:, None], [2])  # clips pool by adding sums
    assert (pooled.boundary_count, pooled.within_count) == (3, 7)
    assert pooled.ratio() == pytest.approx((11 / 3) / (7 / 7))
    assert JumpSums().ratio() is None and chunk_jumps(np.zeros((4, 2)), [2]).ratio() is None  # frozen
    with pytest.raises(ValueError, match="pass starts must be frames 1..7"):
        chunk_jumps(frames, [0])
