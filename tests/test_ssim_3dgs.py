"""`morphgs.metrics.ssim_3dgs`, the training losses' SSIM: INRIA 3DGS's definition (zero 'same'
padding), value and gradient, on the native kernel (CPU float32 RGB) and on the torch path,
against a float64 reference written from INRIA's `utils/loss_utils.py`; the same bits for any
thread count; bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from metrics_data import guitar_pair

from morphgs import _core, metrics
from morphgs.metrics import MetricError


def inria_ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM of (N, C, H, W) images as INRIA's `ssim` (float64, autograd)."""
    c = x.shape[1]
    d = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(d**2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] @ g[None, :]).expand(c, 1, 11, 11).contiguous()
    mu1, mu2 = F.conv2d(x, w, padding=5, groups=c), F.conv2d(y, w, padding=5, groups=c)
    s11 = F.conv2d(x * x, w, padding=5, groups=c) - mu1**2
    s22 = F.conv2d(y * y, w, padding=5, groups=c) - mu2**2
    s12 = F.conv2d(x * y, w, padding=5, groups=c) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    return smap.mean(dim=(1, 2, 3))


def _frames() -> tuple[torch.Tensor, torch.Tensor]:
    """Four frames of a real render pair (the guitar scene, clean and perturbed), (N, 3, H, W)."""
    pair = guitar_pair()

    def chw(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.clip(a, 0, 1), np.float32)).permute(0, 3, 1, 2)

    return chw(pair.corrupted.rgb[:4]), chw(pair.clean.rgb[:4])


def _check_against_reference(x: torch.Tensor, y: torch.Tensor, *, atol: float, grad_rtol: float) -> None:
    xg = x.clone().requires_grad_()
    ours = metrics.ssim_3dgs(xg, y, reduction="none")
    (g,) = torch.autograd.grad(ours.sum(), xg)
    xr = x.detach().double().requires_grad_()
    ref = inria_ssim(xr, y.double())
    (gr,) = torch.autograd.grad(ref.sum(), xr)
    np.testing.assert_allclose(ours.detach().double().numpy(), ref.detach().numpy(), rtol=0, atol=atol)
    scale = gr.abs().max().item()
    assert scale > 0
    np.testing.assert_allclose(g.double().numpy(), gr.numpy(), rtol=0, atol=grad_rtol * scale)


def test_native_kernel_matches_inria_in_value_and_gradient_on_real_renders() -> None:
    x, y = _frames()
    assert x.dtype == torch.float32 and x.shape[1] == 3  # the native path
    _check_against_reference(x, y, atol=2e-6, grad_rtol=1e-4)
    # and an odd size, where the window overhangs every border
    g = torch.Generator().manual_seed(1)
    t = torch.rand(2, 3, 13, 21, generator=g)
    p = (0.8 * t + 0.1 + 0.05 * torch.randn(t.shape, generator=g)).clamp(0, 1)
    _check_against_reference(p, t, atol=2e-6, grad_rtol=1e-4)


@pytest.mark.parametrize("case", ["float64", "four channels", "target with gradient"])
def test_torch_path_matches_inria_where_the_native_kernel_does_not_apply(case: str) -> None:
    x, y = _frames()
    if case == "float64":
        _check_against_reference(x.double(), y.double(), atol=1e-12, grad_rtol=1e-10)
        return
    if case == "four channels":
        x4, y4 = torch.cat([x, x[:, :1]], 1), torch.cat([y, y[:, :1]], 1)
        _check_against_reference(x4, y4, atol=2e-6, grad_rtol=1e-4)
        return
    yg = y.clone().requires_grad_()
    val = metrics.ssim_3dgs(x, yg)
    (gy,) = torch.autograd.grad(val, yg)
    assert gy.abs().max() > 0  # the target's gradient flows on the torch path
    assert float(val.detach()) == pytest.approx(float(inria_ssim(x.double(), y.double()).mean()), abs=2e-6)


def test_reduction_leading_dims_identity_and_the_evaluation_ssim() -> None:
    x, y = _frames()
    clip_x, clip_y = x.reshape(2, 2, *x.shape[1:]), y.reshape(2, 2, *y.shape[1:])
    per = metrics.ssim_3dgs(clip_x, clip_y, reduction="none")
    assert per.shape == (2, 2)
    assert float(metrics.ssim_3dgs(clip_x, clip_y)) == pytest.approx(float(per.mean()), abs=1e-7)
    assert float(metrics.ssim_3dgs(y, y)) == pytest.approx(1.0, abs=1e-6)
    # the evaluation SSIM (reflect padding, torchmetrics) differs from it only near the borders
    a, b = float(metrics.ssim_3dgs(x, y)), float(metrics.ssim(x, y))
    assert a != b and abs(a - b) < 0.02


_WORKER = """
import hashlib, json, sys
import numpy as np
from morphgs import _core
rng = np.random.default_rng(7)
t = rng.random((5, 37, 45, 3), dtype=np.float32)
p = np.clip(t + rng.normal(0, 0.1, t.shape), 0, 1).astype(np.float32)
v, g = _core._ssim_batch(p, t, grad=True)
v2, none = _core._ssim_batch(p, t, grad=False)
assert none is None and np.abs(v - v2).max() < 1e-8  # the value without the gradient's pass
print(json.dumps([hashlib.sha256(a.tobytes()).hexdigest() for a in (v, g, v2)]))
"""


def test_native_kernel_gives_the_same_bytes_for_1_2_and_8_threads_and_each_simd_level() -> None:
    out = set()
    for threads, simd in [("1", None), ("2", None), ("8", None), ("2", "avx2"), ("1", "scalar")]:
        env = {**os.environ, "MORPHGS_NUM_THREADS": threads}
        if simd:
            env["MORPHGS_SIMD"] = simd
        r = subprocess.run([sys.executable, "-c", _WORKER], env=env, capture_output=True, text=True, check=True)
        out.add(tuple(json.loads(r.stdout)))
    assert len(out) == 1


def test_bad_input_is_refused_with_a_clear_error() -> None:
    x, y = _frames()
    with pytest.raises(MetricError, match="shapes differ"):
        metrics.ssim_3dgs(x, y[:, :, :-1])
    with pytest.raises(MetricError, match="two torch tensors"):
        metrics.ssim_3dgs(x.numpy(), y.numpy())
    with pytest.raises(MetricError, match="reduction"):
        metrics.ssim_3dgs(x, y, reduction="sum")
    a = np.zeros((2, 8, 8, 3), np.float32)
    with pytest.raises(ValueError, match=r"\(N, H, W, 3\)"):
        _core._ssim_batch(a, np.zeros((2, 8, 9, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(N, H, W, 3\)"):
        _core._ssim_batch(np.zeros((2, 8, 8, 4), np.float32), np.zeros((2, 8, 8, 4), np.float32))
    with pytest.raises(ValueError, match="C-contiguous"):
        _core._ssim_batch(np.asfortranarray(a), a)
    with pytest.raises(ValueError, match="at least 1x1"):
        _core._ssim_batch(np.zeros((1, 0, 8, 3), np.float32), np.zeros((1, 0, 8, 3), np.float32))
