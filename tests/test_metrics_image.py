"""PSNR and SSIM: hand-computed values, invariances, torchmetrics' SSIM, masks, bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from metrics_data import guitar_pair
from skimage.metrics import structural_similarity
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

import morphgs
from morphgs import metrics
from morphgs.metrics import MetricError
from morphgs.metrics.image import SSIM_K1, SSIM_K2, _blur_cv2, _blur_numpy, ssim_map_numpy


def _clip_pair() -> tuple[np.ndarray, np.ndarray]:
    pair = guitar_pair()
    return np.clip(pair.corrupted.rgb, 0, 1), np.clip(pair.clean.rgb, 0, 1)


def _chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a)).permute(0, 3, 1, 2)


# ---- PSNR ----

def test_psnr_hand_computed_values() -> None:
    x = np.zeros((2, 8, 8, 3))
    y = np.full((2, 8, 8, 3), 0.1)
    assert metrics.psnr(x, y) == pytest.approx(20.0)                      # MSE 0.01
    assert metrics.psnr(x, y, data_range=2.0) == pytest.approx(20.0 + 20 * np.log10(2))
    u0, u1 = np.zeros((4, 4, 3), np.uint8), np.full((4, 4, 3), 255, np.uint8)
    assert metrics.psnr(u0, u1) == pytest.approx(0.0)                     # uint8 means /255: MSE 1
    t = metrics.psnr(torch.zeros(3, 8, 8), torch.full((3, 8, 8), 0.1))
    assert isinstance(t, torch.Tensor) and t.ndim == 0 and float(t) == pytest.approx(20.0, abs=1e-4)


def test_psnr_is_per_frame_then_averaged() -> None:
    x = np.zeros((2, 4, 4, 1))
    y = np.stack([np.full((4, 4, 1), 0.1), np.full((4, 4, 1), 0.01)])    # 20 dB and 40 dB
    np.testing.assert_allclose(metrics.psnr(x, y, reduction="none"), [20.0, 40.0])
    assert metrics.psnr(x, y) == pytest.approx(30.0)                      # not the PSNR of the mean MSE


def test_psnr_of_identical_images_is_inf_without_warnings() -> None:
    pred, _ = _clip_pair()
    assert metrics.psnr(pred, pred) == np.inf
    assert np.all(metrics.psnr(pred, pred, reduction="none") == np.inf)
    assert float(metrics.psnr(_chw(pred), _chw(pred))) == np.inf


def test_psnr_matches_torchmetrics_per_frame() -> None:
    pred, gt = _clip_pair()
    ours = metrics.psnr(pred, gt, reduction="none")
    ref = [float(PeakSignalNoiseRatio(data_range=1.0)(_chw(pred[i:i + 1]).double(), _chw(gt[i:i + 1]).double()))
           for i in range(len(pred))]
    np.testing.assert_allclose(ours, ref, rtol=1e-6)
    np.testing.assert_allclose(metrics.psnr(_chw(pred), _chw(gt), reduction="none").numpy(), ours, rtol=1e-5)


def test_psnr_mask_ignores_pixels_outside_it_and_empty_masks_give_nan() -> None:
    x = np.zeros((2, 6, 6, 3))
    y = np.full_like(x, 0.1)
    y[:, :, 3:] = 0.9                                                     # the right half differs a lot
    mask = np.zeros((6, 6), bool)
    mask[:, :3] = True
    assert metrics.psnr(x, y, mask=mask) == pytest.approx(20.0)
    per_frame_mask = np.stack([mask, np.zeros_like(mask)])
    vals = metrics.psnr(x, y, mask=per_frame_mask, reduction="none")
    assert vals[0] == pytest.approx(20.0) and np.isnan(vals[1])
    assert metrics.psnr(x, y, mask=per_frame_mask) == pytest.approx(20.0)  # the mean skips the empty frame
    t = metrics.psnr(torch.from_numpy(x).permute(0, 3, 1, 2), torch.from_numpy(y).permute(0, 3, 1, 2),
                     mask=torch.from_numpy(per_frame_mask), reduction="none")
    assert float(t[0]) == pytest.approx(20.0) and bool(t[1].isnan())


# ---- SSIM ----

def test_ssim_of_constant_images_is_the_luminance_term() -> None:
    a, b = 0.3, 0.7
    x, y = np.full((16, 16, 3), a), np.full((16, 16, 3), b)
    c1 = SSIM_K1**2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    assert metrics.ssim(x, y) == pytest.approx(expected, rel=1e-9)                        # float64 in, float64 out
    assert metrics.ssim(x.astype(np.float32), y.astype(np.float32)) == pytest.approx(expected, abs=2e-4)
    assert float(metrics.ssim(torch.from_numpy(x).permute(2, 0, 1), torch.from_numpy(y).permute(2, 0, 1))) == \
        pytest.approx(expected, rel=1e-9)


def test_ssim_of_identical_images_is_one() -> None:
    pred, _ = _clip_pair()
    np.testing.assert_allclose(metrics.ssim(pred, pred, reduction="none"), 1.0, atol=1e-6)
    assert float(metrics.ssim(_chw(pred), _chw(pred))) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_matches_torchmetrics_on_real_renders(dtype: torch.dtype) -> None:
    pred, gt = _clip_pair()
    noisy = np.clip(gt + np.random.default_rng(0).normal(0, 0.05, gt.shape), 0, 1)
    for p in (pred, noisy):
        ref = StructuralSimilarityIndexMeasure(data_range=1.0, reduction="none")(_chw(p).to(dtype), _chw(gt).to(dtype))
        ours_t = metrics.ssim(_chw(p).to(dtype), _chw(gt).to(dtype), reduction="none")
        ours_n = metrics.ssim(p.astype(np.float64), gt.astype(np.float64), reduction="none")
        np.testing.assert_allclose(ours_t.numpy(), ref.numpy(), atol=1e-6 if dtype == torch.float64 else 2e-5)
        np.testing.assert_allclose(ours_n, ref.numpy(), atol=2e-5)
        assert metrics.ssim(p, gt) == pytest.approx(float(ref.mean()), abs=2e-5)


@pytest.mark.parametrize("shape", [(2, 3, 128, 128), (1, 3, 96, 130), (3, 3, 7, 9)])
def test_ssim_matrix_blur_is_the_padded_convolution_and_its_gradient(
        shape: tuple[int, ...], monkeypatch: pytest.MonkeyPatch) -> None:
    """Torch images up to 512 pixels a side blur by two matrix products (the training loss's fast
    path); the SSIM and its gradient equal the grouped 11x11 convolution's within float rounding."""
    from morphgs.metrics import image

    b = image.blur_matrix(9)
    v = np.random.default_rng(3).random(9)
    want = np.convolve(np.pad(v, 5, mode="reflect"), image.gaussian_window(np.float64), mode="valid")
    np.testing.assert_allclose(b @ v, want, atol=1e-15)
    np.testing.assert_allclose(b.sum(axis=1), 1.0, atol=1e-15)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    y = (x.detach() + 0.1 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    out = {}
    for limit in (512, 0):  # the matrix path, then the convolution
        monkeypatch.setattr(image, "MATRIX_BLUR_MAX", limit)
        val = metrics.ssim(x, y, reduction="none")
        (grad,) = torch.autograd.grad(val.sum(), x)
        out[limit] = (val.detach(), grad)
    torch.testing.assert_close(out[512][0], out[0][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[512][1], out[0][1], rtol=0, atol=1e-12)
    assert not torch.equal(out[512][0], torch.ones_like(out[512][0]))


def test_ssim_numpy_blur_equals_the_opencv_blur() -> None:
    img = np.random.default_rng(1).random((13, 21, 3), dtype=np.float32)
    np.testing.assert_allclose(_blur_numpy(img), _blur_cv2(img), atol=1e-6)
    wide = np.random.default_rng(2).random((9, 10, 6), dtype=np.float32)   # more channels than OpenCV's 4
    np.testing.assert_allclose(_blur_numpy(wide), _blur_cv2(wide), atol=1e-6)


def test_ssim_is_scikit_image_gaussian_ssim_without_its_border_crop() -> None:
    pred, gt = (a[0].astype(np.float64) for a in _clip_pair())
    sk = structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                               data_range=1.0, channel_axis=-1)
    smap = ssim_map_numpy(pred.astype(np.float32), gt.astype(np.float32), SSIM_K1**2, SSIM_K2**2)
    assert smap[5:-5, 5:-5].mean() == pytest.approx(sk, abs=1e-5)      # skimage crops 5 pixels each side
    assert abs(metrics.ssim(pred, gt) - sk) > 1e-4                      # so the full-image mean differs


def test_ssim_decreases_with_noise_and_uint8_means_div_255() -> None:
    _, gt = _clip_pair()
    rng = np.random.default_rng(3)
    vals = [metrics.ssim(np.clip(gt + rng.normal(0, s, gt.shape), 0, 1), gt) for s in (0.01, 0.05, 0.2)]
    assert vals[0] > vals[1] > vals[2]
    g8 = np.rint(gt * 255).astype(np.uint8)
    p8 = np.rint(np.clip(gt + 0.05, 0, 1) * 255).astype(np.uint8)
    assert metrics.ssim(p8, g8) == pytest.approx(metrics.ssim(p8 / 255.0, g8 / 255.0), abs=1e-6)
    assert metrics.psnr(p8, g8) == pytest.approx(metrics.psnr(p8 / 255.0, g8 / 255.0), rel=1e-9)


def test_ssim_mask_weights_pixels() -> None:
    pred, gt = _clip_pair()
    keep = np.zeros(gt.shape[1:3], bool)
    keep[:, : gt.shape[2] // 2] = True
    damaged = pred.copy()
    damaged[:, :, gt.shape[2] // 2 + 8:] = 0.0                         # only outside the mask (beyond the window)
    np.testing.assert_allclose(metrics.ssim(damaged, gt, mask=keep, reduction="none"),
                               metrics.ssim(pred, gt, mask=keep, reduction="none"), atol=1e-6)
    t = metrics.ssim(_chw(damaged), _chw(gt), mask=torch.from_numpy(keep), reduction="none")
    np.testing.assert_allclose(t.numpy(), metrics.ssim(pred, gt, mask=keep, reduction="none"), atol=2e-5)


def test_one_minus_ssim_is_a_loss_that_trains() -> None:
    torch.manual_seed(0)
    _, gt = _clip_pair()
    target = _chw(gt[:1]).float()
    x = (target + 0.2 * torch.randn_like(target)).clamp(0, 1).requires_grad_(True)
    opt = torch.optim.Adam([x], lr=0.03)
    first = None
    for _ in range(10):
        loss = 1 - metrics.ssim(x, target)
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        assert torch.isfinite(x.grad).all()
        opt.step()
    assert float(1 - metrics.ssim(x.detach(), target)) < 0.7 * first
    val = metrics.psnr(x.detach(), target)
    assert val.ndim == 0 and float(val) > float(metrics.psnr(torch.zeros_like(target), target))


def test_leading_dimensions_are_images() -> None:
    pred, gt = _clip_pair()
    both = metrics.ssim(np.stack([pred, gt]), np.stack([gt, gt]), reduction="none")
    assert both.shape == (2, len(gt))
    np.testing.assert_allclose(both[0], metrics.ssim(pred, gt, reduction="none"))
    assert np.asarray(metrics.psnr(pred[0], gt[0], reduction="none")).shape == ()


def test_bad_input_is_a_clear_metric_error() -> None:
    a = np.zeros((2, 16, 16, 3))
    with pytest.raises(MetricError, match="shapes differ"):
        metrics.psnr(a, a[:1])
    with pytest.raises(MetricError, match="channels-last"):
        metrics.ssim(np.zeros((2, 3, 16, 16)), np.zeros((2, 3, 16, 16)))
    with pytest.raises(MetricError, match="not one of each"):
        metrics.ssim(a, torch.zeros(2, 3, 16, 16))
    with pytest.raises(MetricError, match="at least 6x6"):
        metrics.ssim(np.zeros((5, 5, 3)), np.zeros((5, 5, 3)))
    with pytest.raises(MetricError, match="reduction"):
        metrics.psnr(a, a, reduction="sum")
    with pytest.raises(MetricError, match="does not broadcast"):
        metrics.psnr(a, a, mask=np.ones((4, 4), bool))
    with pytest.raises(MetricError, match="uint8 or floating"):
        metrics.psnr(a.astype(np.int32), a.astype(np.int32))
    assert issubclass(MetricError, morphgs.MorphgsError) and issubclass(MetricError, ValueError)


def test_import_metrics_does_not_import_torch() -> None:
    code = ("import sys, numpy as np, morphgs.metrics as m, morphgs.evaluation; x = np.zeros((8, 8, 3)); "
            "m.psnr(x, x); m.ssim(x, x); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
