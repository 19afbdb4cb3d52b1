"""Depth-map errors (Eigen et al. 2014), as monodepth2's `compute_depth_errors` computes them.

Over the valid pixels of each map (target depth d* > min_depth, finite, below max_depth if given,
pred finite, and the mask), with pred d clipped to [min_depth, max_depth] after alignment:

    AbsRel  = mean(|d - d*| / d*)          SqRel = mean((d - d*)^2 / d*)
    RMSE    = sqrt(mean((d - d*)^2))       RMSElog = sqrt(mean((log d - log d*)^2))
    delta_k = mean(max(d / d*, d* / d) < 1.25^k),  k = 1, 2, 3

Values are per map, then averaged over maps (reduction="mean"). Optional per-map alignment of a
scale-ambiguous prediction before the errors: "median" (d <- d * median(d*) / median(d),
monodepth2's median scaling) or "lstsq" (least-squares scale s and shift b minimising
sum (s d + b - d*)^2, MiDaS-style). Renders of one scene share its scale and need none.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A

__all__ = ["DEPTH_METRICS", "depth_metrics"]

DEPTH_METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "delta1", "delta2", "delta3")
ALIGNMENTS = (None, "median", "lstsq")


def depth_metrics(
    pred: Any,
    target: Any,
    *,
    mask: Any = None,
    align: str | None = None,
    min_depth: float = 1e-3,
    max_depth: float | None = None,
    reduction: str = "mean",
) -> dict[str, Any]:
    """AbsRel, SqRel, RMSE, RMSE log and delta < 1.25^k of depth maps (see the module docstring).

    Args:
        pred, target: (..., H, W) depth maps (numpy or torch, read as numpy), same shape.
        mask: optional (..., H, W) boolean mask of pixels to score (with the validity rules).
        align: None, "median" or "lstsq" (per map).
        min_depth, max_depth: the valid target range; predictions are clipped to it.
        reduction: "mean" (floats) or "none" (arrays of shape (...,), NaN for a map with no
            valid pixel).

    Returns:
        {"abs_rel", "sq_rel", "rmse", "rmse_log", "delta1", "delta2", "delta3"} -> value.

    Raises:
        MetricError: mismatched shapes, a bad mask, alignment or range.
    """
    A.check_reduction(reduction)
    if align not in ALIGNMENTS:
        raise A.MetricError(f"depth_metrics: align must be one of {ALIGNMENTS}, got {align!r}")
    if not (min_depth > 0) or (max_depth is not None and not max_depth > min_depth):
        raise A.MetricError(f"depth_metrics: need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    p, t = (_as_numpy(a) for a in (pred, target))
    if p.shape != t.shape:
        raise A.MetricError(f"depth_metrics: pred and target shapes differ: {p.shape} vs {t.shape}")
    if p.ndim < 2:
        raise A.MetricError(f"depth_metrics: depth maps are (..., H, W), got shape {p.shape}")
    lead, hw = p.shape[:-2], p.shape[-2:]
    m = A.numpy_mask(None if mask is None else np.asarray(_as_numpy(mask), dtype=bool), lead, hw,
                     name="depth_metrics")
    n = math.prod(lead)
    p, t = p.reshape(n, -1), t.reshape(n, -1)
    mm = None if m is None else m.reshape(n, -1) > 0
    hi = np.inf if max_depth is None else float(max_depth)
    out = {k: np.full(n, np.nan) for k in DEPTH_METRICS}
    for i in range(n):
        ti, pi = t[i], p[i]
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(ti) & np.isfinite(pi) & (ti > min_depth) & (ti < hi)
        if mm is not None:
            valid &= mm[i]
        if not valid.any():
            continue
        row = _errors(_align(pi[valid], ti[valid], align), ti[valid], min_depth, hi)
        for k, v in row.items():
            out[k][i] = v
    return {k: A.reduce_numpy(v.reshape(lead), reduction) for k, v in out.items()}


def _as_numpy(a: Any) -> np.ndarray:
    if A.is_tensor(a):
        a = a.detach().cpu().numpy()
    arr = np.asarray(a)
    if arr.dtype != bool and not np.issubdtype(arr.dtype, np.number):
        raise A.MetricError(f"depth_metrics: depth must be numeric, got {arr.dtype}")
    return arr.astype(np.float64) if arr.dtype != bool else arr


def _align(d: np.ndarray, gt: np.ndarray, align: str | None) -> np.ndarray:
    if align == "median":
        md = np.median(d)
        return d * (np.median(gt) / md) if md > 0 else d
    if align == "lstsq":
        a = np.stack([d, np.ones_like(d)], axis=1)
        (s, b), *_ = np.linalg.lstsq(a, gt, rcond=None)
        return s * d + b
    return d


def _errors(d: np.ndarray, gt: np.ndarray, lo: float, hi: float) -> dict[str, float]:
    d = np.clip(d, lo, hi)
    ratio = np.maximum(d / gt, gt / d)
    diff = d - gt
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(d) - np.log(gt)) ** 2))),
        "delta1": float(np.mean(ratio < 1.25)),
        "delta2": float(np.mean(ratio < 1.25**2)),
        "delta3": float(np.mean(ratio < 1.25**3)),
    }
