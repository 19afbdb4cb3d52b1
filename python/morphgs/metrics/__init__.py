"""Evaluation metrics: every number the paper reports, offline, on a CPU (see docs/metrics.md).

Image metrics take numpy arrays (..., H, W, C), channels-last as `morphgs.media.read_clip` gives
them (uint8 means / 255), or torch tensors (..., C, H, W), torchmetrics' layout, which stay
differentiable. Importing this package never imports torch; torch is imported only for torch
inputs.

    from morphgs import metrics
    metrics.psnr(pred, gt)                     # dB, per frame then averaged
    metrics.ssim(pred, gt, reduction="none")   # per frame, torchmetrics' SSIM
"""

from __future__ import annotations

from morphgs.metrics._arrays import MetricError
from morphgs.metrics.image import psnr, ssim

__all__ = ["MetricError", "psnr", "ssim"]
