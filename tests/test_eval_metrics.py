"""Quality metrics against known values (world_model.eval.metrics)."""

import math

import numpy as np
import pytest

from world_model.eval.metrics import (
    ChangeSums,
    JumpSums,
    SsimConfig,
    chamfer_distance,
    chunk_jumps,
    clip_window_features,
    confusion_sums,
    frechet_distance,
    frechet_features,
    frechet_judge_clip,
    frechet_judge_frame,
    lagged_change,
    lidar_points,
    lidar_range_mae,
    lidar_region_errors,
    long_horizon_ratio,
    masked_psnr,
    masked_range_mae,
    motion_ratio,
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


def test_psnr_of_a_constant_difference_is_20_log10_of_range_over_d():
    """Images differing by d at every pixel and channel: MSE = d^2, so PSNR = 10 log10(255^2 / d^2)
    = 20 log10(255 / d); one value per image of a batch (..., H, W, C); 1/d^2 scaling for data_range."""
    ds = np.array([[1, 5, 17], [50, 85, 255]])
    target = np.zeros((*ds.shape, 8, 12, 3), dtype=np.uint8)
    generated = (target + ds[..., None, None, None]).astype(np.uint8)
    got = psnr(generated, target)
    assert got.shape == ds.shape
    np.testing.assert_allclose(got, 20 * np.log10(255.0 / ds), rtol=0, atol=1e-12)
    assert got[1, 2] == 0.0 and got[0, 0] == pytest.approx(48.1308036, abs=1e-6)  # 20 log10(255)
    np.testing.assert_allclose(psnr(target, generated), got, rtol=0, atol=0)  # symmetric
    # Half the pixels off by d, the rest equal: MSE = d^2 / 2, i.e. +10 log10(2) dB.
    half = target[0, 1].copy()
    half[:4] = 5
    assert psnr(half, target[0, 1]) == pytest.approx(20 * math.log10(255 / 5) + 10 * math.log10(2), abs=1e-12)
    # Float images in [0, 1] off by 0.1: 20 log10(1 / 0.1) = 20 dB with data_range=1.
    f = np.full((4, 4, 3), 0.3)
    assert psnr(f + 0.1, f, data_range=1.0) == pytest.approx(20.0, abs=1e-9)


def _ssim_luminance(a, b, c1=(0.01 * 255) ** 2):
    return (2 * a * b + c1) / (a * a + b * b + c1)


def test_ssim_of_constant_images_is_the_luminance_term():
    """SSIM map (Wang et al. 2004) = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sxx + syy + C2)),
    with C1 = (0.01 L)^2 = 6.5025, C2 = (0.03 L)^2, L = 255, statistics under the normalized Gaussian
    window. For constant grey images x = a, y = b (luma = the grey value: BT.601 weights sum to 1) the
    window means are a and b at every pixel, borders included (reflected constant), and all variances
    and the covariance are 0, so the contrast-structure factor is C2 / C2 = 1 and SSIM is exactly
    (2 a b + C1) / (a^2 + b^2 + C1) everywhere, e.g. a = 100, b = 150: 30006.5025 / 32506.5025."""
    pairs = [(100, 150), (0, 255), (10, 20), (200, 201), (0, 1), (128, 128)]
    x = np.stack([np.full((24, 40, 3), a, dtype=np.uint8) for a, _ in pairs])
    y = np.stack([np.full((24, 40, 3), b, dtype=np.uint8) for _, b in pairs])
    want = np.array([_ssim_luminance(float(a), float(b)) for a, b in pairs])
    assert want[0] == pytest.approx(30006.5025 / 32506.5025, abs=1e-15)
    assert want[1] == pytest.approx(6.5025 / (255**2 + 6.5025), abs=1e-15)  # black vs white: ~1e-4
    np.testing.assert_allclose(ssim(x, y), want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ssim(y, x), want, rtol=0, atol=1e-9)


def test_ssim_with_a_one_pixel_window_is_the_per_pixel_luminance_term():
    """With a 1x1 window each pixel is its own window: mx = x, my = y, variances and covariance 0,
    so the SSIM map is (2 x y + C1) / (x^2 + y^2 + C1) per pixel (on luma) and SSIM is its mean: the
    contrast change y = 128 + (x - 128) / 2 of a grey ramp x then has a hand-computable value."""
    ramp = np.tile(np.linspace(0, 255, 64).round().astype(np.uint8)[None, :, None], (8, 1, 3))
    low_contrast = (128 + (ramp.astype(np.int64) - 128) // 2).astype(np.uint8)
    x, y = ramp[..., 0].astype(np.float64), low_contrast[..., 0].astype(np.float64)
    want = np.mean(_ssim_luminance(x, y))
    got = ssim(low_contrast, ramp, SsimConfig(window=1))
    assert got == pytest.approx(want, abs=1e-12) and 0.5 < want < 0.99
    # Colour: on luma 0.299 R + 0.587 G + 0.114 B.
    rgb = np.random.default_rng(4).integers(0, 256, size=(2, 6, 9, 3)).astype(np.uint8)
    luma = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    want = np.mean(_ssim_luminance(luma[0], luma[1]))
    assert ssim(rgb[0], rgb[1], SsimConfig(window=1)) == pytest.approx(want, abs=1e-12)


def _reference_ssim(x, y, sigma=1.5, radius=5, k1=0.01, k2=0.03, L=255.0):
    """Straight from the definition: an explicitly normalized 11x11 Gaussian window, the image padded
    by mirroring with the edge repeated (OpenCV's BORDER_REFLECT), window sums taken directly."""
    u = np.arange(-radius, radius + 1)
    w1 = np.exp(-(u**2) / (2 * sigma**2))
    w = np.outer(w1, w1) / np.outer(w1, w1).sum()

    def blur(img):
        views = np.lib.stride_tricks.sliding_window_view(np.pad(img, radius, mode="symmetric"), w.shape)
        return np.einsum("ijkl,kl->ij", views, w)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = (k1 * L) ** 2, (k2 * L) ** 2
    return np.mean((2 * mx * my + c1) * (2 * sxy + c2) / ((mx**2 + my**2 + c1) * (sxx + syy + c2)))


def _grey_cases():
    rng = np.random.default_rng(7)
    x = np.clip(rng.normal(128, 40, size=(40, 56)), 0, 255).round()
    yy, xx = np.mgrid[0:40, 0:56]
    ramp = (255 * xx / 55).round()
    return [
        (x, np.clip(x + rng.normal(0, 20, x.shape), 0, 255).round()),  # noise
        (x, (128 + (x - 128) * 0.5).round()),  # contrast halved
        (ramp, (0.6 * ramp).round()),  # brightness-scaled ramp
        (ramp, np.clip(ramp + 30 * np.sin(yy / 3.0), 0, 255).round()),  # structure change
    ]


def _rgb(grey):
    return np.repeat(grey.astype(np.uint8)[..., None], 3, axis=-1)


def test_ssim_matches_a_direct_reference_implementation():
    """Windowed cases (noise, contrast halved, brightness-scaled ramp, structure change) against
    _reference_ssim, an independent computation of the same definition (grey images: luma = value)."""
    for x, y in _grey_cases():
        want = _reference_ssim(x, y)
        assert ssim(_rgb(y), _rgb(x)) == pytest.approx(want, abs=1e-9)
        assert want < 0.999


def test_ssim_matches_scikit_image():
    """scikit-image's Gaussian-weighted SSIM (Wang et al.: sigma 1.5, truncate 3.5 -> 11 taps,
    population covariances, K1 0.01, K2 0.03) on grey images; its full map's mean over all pixels
    (its own mean crops the 5-pixel border, ours does not)."""
    metrics = pytest.importorskip("skimage.metrics")
    for x, y in _grey_cases():
        _, full = metrics.structural_similarity(
            y, x, data_range=255.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True
        )
        assert ssim(_rgb(y), _rgb(x)) == pytest.approx(float(np.mean(full)), abs=1e-9)


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


def test_lagged_change_and_motion_ratio_against_hand_worked_values():
    frames = np.array([0.0, 1.0, 3.0, 6.0])[:, None] + np.zeros((4, 5))  # a stream speeding up
    assert lagged_change(frames, 1) == ChangeSums(1.0 + 2.0 + 3.0, 3)
    assert lagged_change(frames, 2) == ChangeSums(3.0 + 5.0, 2)
    assert lagged_change(frames, 4) == ChangeSums(0.0, 0)  # no pair that far apart
    frozen = lagged_change(np.repeat(frames[:1], 4, axis=0), 1)
    assert frozen == ChangeSums(0.0, 3)
    recording = lagged_change(frames, 1)
    assert motion_ratio(recording, recording) == 1.0
    assert motion_ratio(frozen, recording) == 0.0
    assert motion_ratio(lagged_change(2 * frames, 1), recording) == pytest.approx(2.0)  # twice the change
    pooled = recording + lagged_change(np.arange(3.0)[:, None], 1)  # clips pool by adding sums
    assert pooled == ChangeSums(8.0, 5) and pooled.mean() == pytest.approx(1.6)
    assert motion_ratio(ChangeSums(), recording) is None and motion_ratio(recording, frozen) is None
    with pytest.raises(ValueError, match="lag must be >= 1"):
        lagged_change(frames, 0)


def test_masked_psnr_and_range_mae_score_only_the_masked_pixels():
    gt = _images(1)
    gen = gt.copy()
    mask = np.zeros(gt.shape[:-1], bool)
    mask[0, 4:8, 10:20] = True
    gen[~mask] = 0  # outside the mask: anything
    assert masked_psnr(gen, gt, mask) == math.inf
    gen[mask] = np.clip(gt[mask].astype(int) + 5, 0, 255)
    d = (gen[mask].astype(float) - gt[mask]).ravel()
    assert masked_psnr(gen, gt, mask) == pytest.approx(10 * math.log10(255**2 / np.mean(d * d)))
    assert masked_psnr(gen, gt, np.zeros_like(mask)) is None
    with pytest.raises(ValueError, match="mask must be"):
        masked_psnr(gen, gt, mask[0])
    r = np.full((4, 64), 20.0, np.float32)
    lm = np.zeros((4, 64), bool)
    lm[1, 3:7] = True
    far = r + np.where(lm, 3.0, 100.0).astype(np.float32)
    assert masked_range_mae(far, r, lm) == pytest.approx(3.0)
    assert masked_range_mae(far, r, np.zeros_like(lm)) is None
    with pytest.raises(ValueError, match="mask must be"):
        masked_range_mae(far, r, lm[:2])


def test_class_iou_by_hand():
    # 2 x 3 map, classes 0 (road), 1 (vehicle), 2 (sky; never present).
    labels = np.array([[0, 0, 1], [0, 1, 1]])
    predicted = np.array([[0, 1, 1], [0, 0, 1]])
    sums = confusion_sums(predicted, labels, 3)
    # road: labelled {a, b, d}, predicted {a, d, e}: intersection 2, union 4.
    # vehicle: labelled {c, e, f}, predicted {b, c, f}: intersection 2, union 4.
    assert sums.iou() == [0.5, 0.5, None]
    assert sums.accuracy() == [pytest.approx(2 / 3), pytest.approx(2 / 3), None]
    # Sums over frames weigh pixels, not frames: a perfect 1-pixel frame barely moves the IoU.
    total = sums + confusion_sums(np.array([1]), np.array([1]), 3)
    assert total.iou() == [0.5, pytest.approx(3 / 5), None]
    assert confusion_sums(labels, labels, 3).iou() == [1.0, 1.0, None]
    # Everything predicted road: road 3 / 6, vehicle never predicted right (0, not None: it is labelled).
    assert confusion_sums(np.zeros_like(labels), labels, 3).iou() == [0.5, 0.0, None]
    # A class predicted but never labelled has IoU 0 (union > 0), and accuracy None.
    only_pred = confusion_sums(np.array([2, 0]), np.array([0, 0]), 3)
    assert only_pred.iou() == [0.5, None, 0.0] and only_pred.accuracy() == [0.5, None, None]
    with pytest.raises(ValueError, match="outside"):
        confusion_sums(labels + 2, labels, 3)
    with pytest.raises(ValueError, match="same shape"):
        confusion_sums(labels[:1], labels, 3)
    with pytest.raises(ValueError, match="cannot pool"):
        sums + confusion_sums(labels, labels, 4)


def test_lidar_region_errors_split_road_and_object_returns():
    spec = LidarSpec(beams=2, azimuth=4)
    truth = np.array([[10.0, 10.0, 0.0, 20.0], [5.0, 5.0, 5.0, 5.0]], dtype=np.float32)  # one no-return ray
    objects = np.array([[False, True, False, False], [False, False, True, True]])
    gen = truth + np.array([[1.0, 4.0, 7.0, 3.0], [1.0, 1.0, 2.0, 6.0]], dtype=np.float32)
    e = lidar_region_errors(gen, truth, objects, spec)
    # Road: rays (0,0) +1, (0,3) +3, (1,0) +1, (1,1) +1 -> 6 / 4; the no-return ray (0,2) counts nowhere.
    assert e.road_m == pytest.approx(1.5)
    # Objects: (0,1) +4, (1,2) +2, (1,3) +6 -> 12 / 3.
    assert e.objects_m == pytest.approx(4.0)
    assert lidar_region_errors(gen, truth, np.zeros_like(objects), spec).objects_m is None
    with pytest.raises(ValueError, match="object_returns must be bool"):
        lidar_region_errors(gen, truth, objects.astype(np.uint8), spec)
