"""What evaluation works on and gives: the metric table (METRICS), clip pairs and the report type,
apart from `evaluate` (core.py) and the writers (report.py), which both read them."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from morphgs._core import MorphgsError

__all__ = ["DEFAULT_METRICS", "METRICS", "SELECTABLE", "Clip", "ClipPair", "EvalError", "EvalReport", "MetricInfo"]


class EvalError(MorphgsError):
    """Clips that cannot be compared (names them): different sizes or frame counts, bad options."""


@dataclass(frozen=True)
class MetricInfo:
    kind: str           # "frame", "pair" or "depth"
    higher_is_better: bool
    fmt: str
    title: str


_DEPTH = {
    "depth_abs_rel": MetricInfo("depth", False, "{:.4f}", "AbsRel"),
    "depth_sq_rel": MetricInfo("depth", False, "{:.4f}", "SqRel"),
    "depth_rmse": MetricInfo("depth", False, "{:.4f}", "RMSE"),
    "depth_rmse_log": MetricInfo("depth", False, "{:.4f}", "RMSE log"),
    "depth_delta1": MetricInfo("depth", True, "{:.4f}", "δ<1.25"),
    "depth_delta2": MetricInfo("depth", True, "{:.4f}", "δ<1.25²"),
    "depth_delta3": MetricInfo("depth", True, "{:.4f}", "δ<1.25³"),
}
METRICS: dict[str, MetricInfo] = {
    "psnr": MetricInfo("frame", True, "{:.2f}", "PSNR"),
    "ssim": MetricInfo("frame", True, "{:.4f}", "SSIM"),
    "lpips": MetricInfo("frame", False, "{:.4f}", "LPIPS"),
    "color_shift": MetricInfo("frame", False, "{:.2f}", "ΔE colour shift"),
    "eflow": MetricInfo("pair", False, "{:.3f}", "E_flow"),
    "ewarp": MetricInfo("pair", False, "{:.5f}", "E_warp"),
    **_DEPTH,
}
# what `metrics=` names: the image and temporal metrics, and "depth" for the seven depth errors
SELECTABLE = ("psnr", "ssim", "lpips", "color_shift", "eflow", "ewarp", "depth")
DEFAULT_METRICS = ("psnr", "ssim", "lpips", "color_shift", "eflow", "ewarp")

Clip = str | os.PathLike[str] | np.ndarray


@dataclass(frozen=True)
class ClipPair:
    """One prediction and its ground truth.

    Attributes:
        name: the clip's name in the tables (e.g. a pair id).
        pred, gt: a clip path (folder of frames or video) or an (F, H, W, 3) array (uint8, or float
            in [0, 1]).
        depth_pred, depth_gt: optional depth (folder of EXRs or an (F, H, W) array); both are
            needed for the depth errors.
        cameras: optional `morphgs.Cameras` of the frames; with `depth_gt` the exact geometric
            flow of the ground truth replaces DIS as E_flow's and E_warp's reference.
        label: what the prediction is ("pred"; `morphgs eval --run` uses "input" and "output").
    """

    name: str
    pred: Clip
    gt: Clip
    depth_pred: Clip | None = None
    depth_gt: Clip | None = None
    cameras: Any = None
    label: str = "pred"


@dataclass
class EvalReport:
    """What `evaluate` measured (and wrote).

    Attributes:
        metrics: the metric columns, in order.
        rows: one dict per frame: label, clip, frame and each metric (NaN where it has no value).
        clips: one dict per clip: label, clip, frames and each metric's clip mean.
        overall: {label: {metric: mean over all frames of its clips}}.
        files: what was written: {"csv", "markdown", "json", "plots"} -> paths.
    """

    metrics: list[str]
    rows: list[dict[str, Any]] = field(default_factory=list)
    clips: list[dict[str, Any]] = field(default_factory=list)
    overall: dict[str, dict[str, float]] = field(default_factory=dict)
    files: dict[str, Any] = field(default_factory=dict)
