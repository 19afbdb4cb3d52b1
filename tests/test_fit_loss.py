"""The fit's loss against a torch reference: INRIA 3DGS's `l1_loss` and `ssim` (11x11 Gaussian
window, sigma 1.5, zero 'same' padding, utils/loss_utils.py) with autograd for the gradient."""

from __future__ import annotations

import numpy as np
import pytest

from morphgs import _core

torch = pytest.importorskip("torch")
F = torch.nn.functional


def inria_loss(pred: "torch.Tensor", target: "torch.Tensor", lam: float) -> tuple:
    """(1 - lam) L1 + lam (1 - SSIM), written as INRIA's loss_utils.py (float64 here)."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11).contiguous()
    img1, img2 = pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    mu1 = F.conv2d(img1, w, padding=5, groups=3)
    mu2 = F.conv2d(img2, w, padding=5, groups=3)
    s11 = F.conv2d(img1 * img1, w, padding=5, groups=3) - mu1**2
    s22 = F.conv2d(img2 * img2, w, padding=5, groups=3) - mu2**2
    s12 = F.conv2d(img1 * img2, w, padding=5, groups=3) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    ssim = ssim_map.mean()
    l1 = (pred - target).abs().mean()
    return (1 - lam) * l1 + lam * (1 - ssim), l1, ssim


@pytest.mark.parametrize("size", [(23, 17), (70, 41)])
def test_loss_and_gradient_match_inria_ssim_in_float64(size: tuple[int, int]) -> None:
    w, h = size
    rng = np.random.default_rng(w)
    # a smooth image plus noise, and a render that differs from it by a blur and an offset
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.5 + 0.3 * np.sin(xx[..., None] * 0.2 + np.arange(3)) * np.cos(yy[..., None] * 0.15)
    target = np.clip(base + rng.normal(0, 0.05, base.shape), 0, 1).astype(np.float32)
    pred = (base * 0.9 + 0.07 + rng.normal(0, 0.02, base.shape)).astype(np.float32)
    loss, l1, ssim, grad = _core._fit_loss(pred, target, ssim_lambda=0.2)

    p = torch.tensor(pred, dtype=torch.float64, requires_grad=True)
    ref, ref_l1, ref_ssim = inria_loss(p, torch.tensor(target, dtype=torch.float64), 0.2)
    ref.backward()
    assert l1 == pytest.approx(ref_l1.item(), rel=1e-6)
    assert ssim == pytest.approx(ref_ssim.item(), rel=1e-5, abs=1e-6)
    assert loss == pytest.approx(ref.item(), rel=1e-5)
    g_ref = p.grad.numpy()
    # float32 accumulation against float64: relative to the gradient's scale
    scale = np.abs(g_ref).max()
    assert np.abs(grad - g_ref).max() < 1e-4 * scale


def test_ssim_of_identical_images_is_one_and_pure_l1_has_sign_gradient() -> None:
    img = np.random.default_rng(0).random((20, 30, 3), dtype=np.float32)
    loss, l1, ssim, grad = _core._fit_loss(img, img.copy(), ssim_lambda=0.2)
    assert loss == pytest.approx(0.0, abs=1e-6) and l1 == 0.0 and ssim == pytest.approx(1.0, abs=1e-6)
    pred = img + np.float32(0.1)
    _, _, _, g = _core._fit_loss(pred, img, ssim_lambda=0.0)
    np.testing.assert_allclose(g, np.full_like(g, 1.0 / img.size), rtol=1e-6)


def test_bad_shapes_are_refused() -> None:
    a = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="both be"):
        _core._fit_loss(a, np.zeros((8, 9, 3), np.float32))
