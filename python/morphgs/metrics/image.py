"""PSNR and SSIM on numpy arrays (..., H, W, C) or torch tensors (..., C, H, W).

Conventions (both metrics):
- Values are computed per image (the leading dimensions index images, e.g. frames of a clip) and
  `reduction="mean"` averages the per-image values; `"none"` returns them, shape (...,).
- uint8 inputs mean value / 255; `data_range` is the range of the (scaled) values, 1 by default.
- `mask` (..., H, W), boolean or non-negative weights, broadcast over the leading dimensions:
  per-image values are weighted means over the masked pixels (all channels). An image whose mask
  is empty gives NaN, and `"mean"` skips NaN images.
- numpy inputs return numpy / Python floats (computed without torch); torch inputs return tensors
  on their device and stay differentiable (`1 - ssim(x, y)` is a loss).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A

__all__ = ["psnr", "ssim", "ssim_3dgs", "SSIM_K1", "SSIM_K2", "SSIM_SIGMA", "SSIM_WINDOW"]

SSIM_SIGMA = 1.5
SSIM_WINDOW = 11  # torchmetrics: int(3.5 * sigma + 0.5) * 2 + 1
SSIM_K1 = 0.01
SSIM_K2 = 0.03
_PAD = SSIM_WINDOW // 2


def psnr(pred: Any, target: Any, *, data_range: float = 1.0, mask: Any = None, reduction: str = "mean") -> Any:
    """Peak signal-to-noise ratio, 10 log10(data_range^2 / MSE), per image then averaged.

    The MSE of an image is over all its pixels and channels (or the masked pixels, all channels).
    Identical images give +inf (no warning); the mean over images is then +inf as well.

    Args:
        pred, target: numpy (..., H, W, C) or torch (..., C, H, W) images of the same shape;
            uint8 means / 255.
        data_range: the value range (1 for images in [0, 1]).
        mask: optional per-pixel weights (..., H, W).
        reduction: "mean" (a float for numpy, a 0-d tensor for torch) or "none" (per image).

    Returns:
        PSNR in dB.

    Raises:
        MetricError: mismatched shapes, a bad layout, dtype, mask or reduction.
    """
    A.check_reduction(reduction)
    r = A.check_data_range(data_range)
    if A.is_tensor(pred) or A.is_tensor(target):
        return _psnr_torch(pred, target, r, mask, reduction)
    p, t = A.numpy_images(pred, target, name="psnr")
    lead, (h, w, c) = p.shape[:-3], p.shape[-3:]
    m = A.numpy_mask(mask, lead, (h, w), name="psnr")
    n = math.prod(lead)
    p, t = p.reshape(n, h, w, c), t.reshape(n, h, w, c)
    m = None if m is None else m.reshape(n, h, w)
    sq_sum = np.empty(n)
    weight = np.empty(n)
    for i in range(n):  # one image at a time: temporaries stay image-sized
        d, scale = _difference(p[i], t[i])
        if m is None:
            sq_sum[i] = scale * np.einsum("i,i->", d, d, dtype=np.float64)
            weight[i] = h * w
        else:
            se = np.einsum("pc,pc->p", d.reshape(-1, c), d.reshape(-1, c))  # C terms per pixel
            sq_sum[i] = scale * np.dot(se.astype(np.float64), m[i].reshape(-1))
            weight[i] = m[i].sum()
    values = _psnr_from_sums(sq_sum, weight * c, r)
    return A.reduce_numpy(values.reshape(lead), reduction)


def _difference(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Flat a - b and the factor its squares need: uint8 pairs subtract exactly in float32 (then
    / 255^2), float64 inputs in float64, others in float32; sums accumulate in float64."""
    if a.dtype == np.uint8 and b.dtype == np.uint8:
        return np.subtract(a, b, dtype=np.float32).reshape(-1), 1.0 / 255.0**2
    ft = np.float64 if np.float64 in (a.dtype, b.dtype) else np.float32
    return (A.as_float(a, ft) - A.as_float(b, ft)).reshape(-1), 1.0


def _psnr_from_sums(sq_sum: np.ndarray, count: np.ndarray, data_range: float) -> np.ndarray:
    out = np.full(sq_sum.shape, np.nan)
    ok = count > 0
    mse = np.divide(sq_sum, count, out=np.zeros_like(sq_sum), where=ok)
    zero = ok & (mse == 0)
    pos = ok & ~zero
    out[zero] = np.inf
    out[pos] = 10.0 * np.log10(data_range**2 / mse[pos])
    return out


def _psnr_torch(pred: Any, target: Any, r: float, mask: Any, reduction: str) -> Any:
    p, t = A.torch_images(pred, target, name="psnr")
    lead, (c, h, w) = tuple(p.shape[:-3]), tuple(p.shape[-3:])
    m = A.torch_mask(mask, p, lead, (h, w), name="psnr")
    se = (p - t).square().sum(dim=-3)
    if m is None:
        mse = se.mean(dim=(-2, -1)) / c
    else:
        mse = (se * m).sum(dim=(-2, -1)) / (m.sum(dim=(-2, -1)) * c)
    values = 10.0 * (r * r / mse).log10()
    return A.reduce_torch(values, reduction)


def ssim(pred: Any, target: Any, *, data_range: float = 1.0, mask: Any = None, reduction: str = "mean") -> Any:
    """Structural similarity (Wang et al. 2004) as torchmetrics computes it.

    Gaussian window of 11 taps, sigma 1.5, K1 = 0.01, K2 = 0.03, C1 = (K1 L)^2, C2 = (K2 L)^2 with
    L = data_range; each image is reflect-padded by 5 pixels (no edge repeat) so the SSIM map has
    the image's size, variances are clamped at 0, and the map is averaged over every pixel and
    channel — `torchmetrics.image.StructuralSimilarityIndexMeasure(data_range=1)`, the metric of
    3DGS, gsplat and Difix3D evaluations. scikit-image's `structural_similarity` differs: a 7x7
    uniform window by default, sample covariance (N - 1), and a mean over the map with the border
    of half a window cropped; even with `gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False` it crops the border, so its values differ slightly.

    Precision follows the input as in torchmetrics: float64 images are computed in float64,
    others (float32, float16, uint8) in float32, where flat regions carry errors of about 1e-5
    (the variance is E[x^2] - E[x]^2). numpy inputs use OpenCV's separable filter when it is
    installed (else the same filter in numpy) and average in float64; torch inputs blur by two
    matrix products with the padding folded in (up to 512 pixels a side; larger ones by a grouped
    11x11 convolution), the same sums in another order.

    Args:
        pred, target: numpy (..., H, W, C) or torch (..., C, H, W) images of the same shape, at
            least 6x6 pixels; uint8 means / 255.
        data_range: the value range (1 for images in [0, 1]).
        mask: optional per-pixel weights (..., H, W); the SSIM map is averaged over channels,
            then weighted over pixels.
        reduction: "mean" (a float for numpy, a 0-d tensor for torch) or "none" (per image).

    Returns:
        SSIM, 1 for identical images.

    Raises:
        MetricError: mismatched shapes, images under 6x6 pixels, a bad layout, dtype, mask or
            reduction.
    """
    A.check_reduction(reduction)
    r = A.check_data_range(data_range)
    if A.is_tensor(pred) or A.is_tensor(target):
        return _ssim_torch(pred, target, r, mask, reduction)
    p, t = A.numpy_images(pred, target, name="ssim", min_size=_PAD + 1)
    lead, (h, w, c) = p.shape[:-3], p.shape[-3:]
    m = A.numpy_mask(mask, lead, (h, w), name="ssim")
    n = math.prod(lead)
    p, t = p.reshape(n, h, w, c), t.reshape(n, h, w, c)
    m = None if m is None else m.reshape(n, h, w)
    blur = _blur_cv2 if _have_cv2() else _blur_numpy
    c1, c2 = (SSIM_K1 * r) ** 2, (SSIM_K2 * r) ** 2
    ft = np.float64 if np.float64 in (p.dtype, t.dtype) else np.float32
    values = np.empty(n)
    for i in range(n):
        smap = ssim_map_numpy(A.as_float(p[i], ft), A.as_float(t[i], ft), c1, c2, blur)
        pix = smap.mean(axis=-1, dtype=np.float64)
        if m is None:
            values[i] = pix.mean()
        else:
            wsum = m[i].sum()
            values[i] = np.einsum("hw,hw->", pix, m[i]) / wsum if wsum > 0 else np.nan
    return A.reduce_numpy(values.reshape(lead), reduction)


def ssim_3dgs(pred: Any, target: Any, *, reduction: str = "mean") -> Any:
    """Differentiable SSIM in INRIA 3DGS's convention, for training losses on torch images.

    The SSIM of 3DGS training (`utils/loss_utils.py::ssim`, and `morphgs fit`'s loss): the 11-tap
    Gaussian window of sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, each channel on its own, **zero 'same'
    padding** (the window runs off the image into zeros) and no clamping of the variances; the
    mean over pixels and channels. It differs from `ssim` (torchmetrics' evaluation convention:
    reflect padding, variances clamped) only near the borders (within 5 pixels).

    CPU float32 images of 3 channels whose target needs no gradient go through the fit's
    streaming native kernel (value and gradient in one pass, in parallel over images, the same
    bits for any thread count: about 10x faster than `ssim`'s matrix blur forward and backward at
    128x128); anything else (other devices, other channel counts, float64, a target that needs a
    gradient) through grouped convolutions in torch, the same formula. float16 / bfloat16 inputs
    are computed in float32.

    Args:
        pred, target: torch (..., C, H, W) tensors of the same shape, floating point; uint8 means
            / 255 (then without gradient).
        reduction: "mean" (a 0-d tensor) or "none" (per image, shape (...,)).

    Returns:
        SSIM, 1 for identical images; differentiable with respect to `pred` (and `target` on the
        torch path).

    Raises:
        MetricError: not two tensors, mismatched shapes, fewer than 3 dimensions, a bad dtype or
            reduction, an empty image.
    """
    import torch

    A.check_reduction(reduction)
    if not (A.is_tensor(pred) and A.is_tensor(target)):
        raise A.MetricError("ssim_3dgs: pass two torch tensors (..., C, H, W)")
    p, t = A.torch_images(pred, target, name="ssim_3dgs", min_size=1)
    if p.dtype in (torch.float16, torch.bfloat16):
        p, t = p.float(), t.float()
    lead, (c, h, w) = tuple(p.shape[:-3]), tuple(p.shape[-3:])
    x, y = p.reshape(-1, c, h, w), t.reshape(-1, c, h, w)
    native = (x.device.type == "cpu" and x.dtype == torch.float32 and c == 3 and not y.requires_grad)
    values = _native_ssim_function().apply(x, y) if native else _ssim_3dgs_torch(x, y)
    return A.reduce_torch(values.reshape(lead), reduction)


def _ssim_3dgs_torch(x: Any, y: Any) -> Any:
    """Per-image INRIA SSIM of (N, C, H, W) tensors by grouped convolutions (zero padding)."""
    import torch
    import torch.nn.functional as F

    c = x.shape[1]
    g = torch.as_tensor(gaussian_window(np.float64), dtype=x.dtype, device=x.device)
    kernel = (g[:, None] * g[None, :]).expand(c, 1, SSIM_WINDOW, SSIM_WINDOW)
    n = x.shape[0]
    stack = torch.cat([x, y, x * x, y * y, x * y])
    mu_x, mu_y, xx, yy, xy = F.conv2d(stack, kernel, padding=_PAD, groups=c).split(n)
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    smap = ((2 * mu_xy + c1) * (2 * (xy - mu_xy) + c2)) / ((mu_xx + mu_yy + c1) * (xx - mu_xx + yy - mu_yy + c2))
    return smap.mean(dim=(1, 2, 3))


@functools.cache
def _native_ssim_function() -> Any:
    """The autograd Function over `_core._ssim_batch` (built on first use: torch is imported
    only then)."""
    import torch

    from morphgs import _core

    class Ssim3dgsNative(torch.autograd.Function):
        """Per-image SSIM of (N, 3, H, W) float32 CPU tensors by `_core._ssim_batch`."""

        @staticmethod
        def forward(ctx: Any, x: Any, y: Any) -> Any:
            xn = x.detach().permute(0, 2, 3, 1).contiguous().numpy()
            yn = y.detach().permute(0, 2, 3, 1).contiguous().numpy()
            vals, grad = _core._ssim_batch(xn, yn, grad=x.requires_grad)
            if grad is not None:
                ctx.save_for_backward(torch.from_numpy(grad))
            return torch.from_numpy(vals).to(torch.float32)

        @staticmethod
        def backward(ctx: Any, go: Any) -> Any:
            (grad,) = ctx.saved_tensors
            return (go.to(grad.dtype)[:, None, None, None] * grad).permute(0, 3, 1, 2), None

    return Ssim3dgsNative


def gaussian_window(dtype: Any = np.float32) -> np.ndarray:
    """The normalised 1-D SSIM window (11 taps, sigma 1.5), as torchmetrics' `_gaussian`."""
    d = np.arange(SSIM_WINDOW, dtype=np.float64) - _PAD
    g = np.exp(-0.5 * (d / SSIM_SIGMA) ** 2)
    return (g / g.sum()).astype(dtype)


def ssim_map_numpy(x: np.ndarray, y: np.ndarray, c1: float, c2: float, blur: Any = None) -> np.ndarray:
    """The SSIM map (H, W, C) of two float (H, W, C) images (see `ssim` for the conventions)."""
    blur = blur or (_blur_cv2 if _have_cv2() else _blur_numpy)
    mu_x, mu_y = blur(x), blur(y)
    xx, yy, xy = blur(x * x), blur(y * y), blur(x * y)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x = np.maximum(xx - mu_xx, 0)
    var_y = np.maximum(yy - mu_yy, 0)
    cov = xy - mu_xy
    num = (2 * mu_xy + c1) * (2 * cov + c2)
    den = (mu_xx + mu_yy + c1) * (var_x + var_y + c2)
    return num / den


def _have_cv2() -> bool:
    try:
        import cv2  # noqa: F401
    except ImportError:
        return False
    return True


def _blur_cv2(img: np.ndarray) -> np.ndarray:
    """Separable Gaussian blur of an (H, W, C) float image, reflect-101 borders (torch's "reflect")."""
    import cv2

    g = gaussian_window(img.dtype)
    h, w, c = img.shape
    if c <= 4:
        out = cv2.sepFilter2D(img, -1, g, g, borderType=cv2.BORDER_REFLECT_101)
        return out.reshape(h, w, c)
    return np.stack([cv2.sepFilter2D(np.ascontiguousarray(img[..., k]), -1, g, g,
                                     borderType=cv2.BORDER_REFLECT_101) for k in range(c)], axis=-1)


def _blur_numpy(img: np.ndarray) -> np.ndarray:
    """The same blur as `_blur_cv2` in plain numpy (shifted sums over a reflect-padded copy)."""
    g = gaussian_window(img.dtype)
    h, w, _ = img.shape
    p = np.pad(img, ((_PAD, _PAD), (_PAD, _PAD), (0, 0)), mode="reflect")
    rows = np.zeros((h + 2 * _PAD, w) + img.shape[2:], img.dtype)
    for k in range(SSIM_WINDOW):
        rows += g[k] * p[:, k:k + w]
    out = np.zeros_like(img)
    for k in range(SSIM_WINDOW):
        out += g[k] * rows[k:k + h]
    return out


#: Torch images up to this many pixels a side blur by matrix products (`_blur_matrix`), larger
#: ones by the grouped convolution (the dense matrices' cost grows with the side: at 1080x1920
#: the convolution is faster).
MATRIX_BLUR_MAX = 512


def blur_matrix(n: int) -> np.ndarray:
    """The (n, n) float64 matrix of the SSIM window over n samples with reflect (no edge repeat)
    padding: `B @ v` is the padded 11-tap blur of v (n >= 6)."""
    g = gaussian_window(np.float64)
    i = np.arange(n)[:, None] + np.arange(SSIM_WINDOW)[None, :] - _PAD
    j = np.abs(i)
    j = np.where(j >= n, 2 * (n - 1) - j, j)
    m = np.zeros((n, n))
    np.add.at(m, (np.repeat(np.arange(n), SSIM_WINDOW), j.ravel()), np.tile(g, n))
    return m


_MATRICES: dict[tuple[int, str, str], Any] = {}


def _blur_matrix(n: int, dtype: Any, device: Any) -> Any:
    """`blur_matrix(n)` as a torch tensor, cached per size, dtype and device."""
    import torch

    key = (n, str(dtype), str(device))
    if key not in _MATRICES:
        if len(_MATRICES) > 32:
            _MATRICES.clear()
        _MATRICES[key] = torch.as_tensor(blur_matrix(n), dtype=dtype, device=device)
    return _MATRICES[key]


def _ssim_torch(pred: Any, target: Any, r: float, mask: Any, reduction: str) -> Any:
    import torch
    import torch.nn.functional as F

    p, t = A.torch_images(pred, target, name="ssim", min_size=_PAD + 1)
    lead, (c, h, w) = tuple(p.shape[:-3]), tuple(p.shape[-3:])
    m = A.torch_mask(mask, p, lead, (h, w), name="ssim")
    if p.dtype not in (torch.float32, torch.float64):
        p, t = p.float(), t.float()
    x, y = p.reshape(-1, c, h, w), t.reshape(-1, c, h, w)
    n = x.shape[0]
    stack = torch.cat([x, y, x * x, y * y, x * y])
    if max(h, w) <= MATRIX_BLUR_MAX:
        # the blur as two matrix products, B_h S B_w^T, the reflect padding folded into the
        # matrices: the same sums as the convolution (in another order: within 1e-6), 3.4x faster
        # forward and backward than the grouped 11x11 convolution at 128x128 on a CPU
        bh = _blur_matrix(h, x.dtype, x.device)
        bw = bh if w == h else _blur_matrix(w, x.dtype, x.device)
        mu_x, mu_y, xx, yy, xy = torch.matmul(torch.matmul(bh, stack), bw.T).split(n)
    else:
        g = torch.as_tensor(gaussian_window(np.float64), dtype=x.dtype, device=x.device)
        kernel = (g[:, None] * g[None, :]).expand(c, 1, SSIM_WINDOW, SSIM_WINDOW)
        stack = F.pad(stack, (_PAD, _PAD, _PAD, _PAD), mode="reflect")
        mu_x, mu_y, xx, yy, xy = F.conv2d(stack, kernel, groups=c).split(n)
    c1, c2 = (SSIM_K1 * r) ** 2, (SSIM_K2 * r) ** 2
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x = (xx - mu_xx).clamp(min=0)
    var_y = (yy - mu_yy).clamp(min=0)
    cov = xy - mu_xy
    smap = ((2 * mu_xy + c1) * (2 * cov + c2)) / ((mu_xx + mu_yy + c1) * (var_x + var_y + c2))
    pix = smap.mean(dim=1).reshape(lead + (h, w))
    if m is None:
        values = pix.mean(dim=(-2, -1))
    else:
        values = (pix * m).sum(dim=(-2, -1)) / m.sum(dim=(-2, -1))
    return A.reduce_torch(values, reduction)
