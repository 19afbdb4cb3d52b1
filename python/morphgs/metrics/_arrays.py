"""Input handling shared by the image metrics: numpy or torch, layouts, masks, reductions.

numpy images are channels-last (..., H, W, C) — the layout of `morphgs.media.read_clip` and
`morphgs.Render.rgb`; torch images are channels-first (..., C, H, W) — torchmetrics' layout.
uint8 inputs mean value / 255. This module never imports torch: a tensor is recognised through
`sys.modules`, so numpy callers never pay for (or need) torch.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from morphgs._core import MorphgsError

__all__ = ["MetricError", "REDUCTIONS", "is_tensor"]

REDUCTIONS = ("mean", "none")


class MetricError(MorphgsError):
    """Inputs a metric cannot compare: mismatched shapes, wrong layout or dtype, a bad mask."""


def is_tensor(x: Any) -> bool:
    """Whether `x` is a torch tensor (without importing torch)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def check_reduction(reduction: str) -> None:
    if reduction not in REDUCTIONS:
        raise MetricError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}")


def check_data_range(data_range: float) -> float:
    r = float(data_range)
    if not np.isfinite(r) or r <= 0:
        raise MetricError(f"data_range must be a positive number, got {data_range!r}")
    return r


def numpy_images(pred: Any, target: Any, *, name: str, min_size: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Validate a numpy image pair (..., H, W, C) of equal shape; uint8 stays uint8 (scaled later).

    Raises:
        MetricError: different shapes, fewer than 3 dimensions, a channels-first look, a dtype
            that is neither uint8 nor floating, or images smaller than `min_size`.
    """
    if is_tensor(pred) or is_tensor(target):
        raise MetricError(f"{name}: pass two numpy arrays or two torch tensors, not one of each")
    p, t = np.asarray(pred), np.asarray(target)
    if p.shape != t.shape:
        raise MetricError(f"{name}: pred and target shapes differ: {p.shape} vs {t.shape}")
    if p.ndim < 3:
        raise MetricError(f"{name}: numpy images are (..., H, W, C); got shape {p.shape}")
    if p.shape[-1] > 4 and p.shape[-3] in (1, 3, 4):
        raise MetricError(f"{name}: numpy images are channels-last (..., H, W, C); shape {p.shape} "
                          "looks channels-first (pass a torch tensor for (..., C, H, W))")
    for a in (p, t):
        if a.dtype != np.uint8 and not np.issubdtype(a.dtype, np.floating):
            raise MetricError(f"{name}: images must be uint8 or floating point, got {a.dtype}")
    h, w = p.shape[-3], p.shape[-2]
    if h < min_size or w < min_size:
        raise MetricError(f"{name}: images must be at least {min_size}x{min_size} pixels, got {w}x{h}")
    return p, t


def as_float(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """A numpy image as float (`dtype`), uint8 divided by 255."""
    if a.dtype == np.uint8:
        return a.astype(dtype) * dtype(1.0 / 255.0)
    return a.astype(dtype, copy=False)


def numpy_mask(mask: Any, lead: tuple[int, ...], hw: tuple[int, int], *, name: str) -> np.ndarray | None:
    """A per-pixel weight mask (..., H, W) broadcast to lead + (H, W), as float64 (None stays None).

    Raises:
        MetricError: a shape that does not broadcast, or negative / non-finite weights.
    """
    if mask is None:
        return None
    if is_tensor(mask):
        mask = mask.detach().cpu().numpy()
    m = np.asarray(mask)
    if m.dtype == bool:
        m = m.astype(np.float64)
    elif np.issubdtype(m.dtype, np.number):
        m = m.astype(np.float64)
        if not np.all(np.isfinite(m)) or np.any(m < 0):
            raise MetricError(f"{name}: mask weights must be finite and >= 0")
    else:
        raise MetricError(f"{name}: mask must be boolean or numeric, got {m.dtype}")
    try:
        return np.broadcast_to(m, lead + hw)
    except ValueError:
        raise MetricError(f"{name}: mask of shape {m.shape} does not broadcast to the images' "
                          f"(..., H, W) = {lead + hw}") from None


def reduce_numpy(values: np.ndarray, reduction: str) -> np.ndarray | float:
    """Per-image values -> "none": the array; "mean": the mean of the finite-or-infinite, non-NaN
    values as a float (NaN marks an image whose mask is empty; all-NaN gives NaN)."""
    if reduction == "none":
        return values
    v = values[~np.isnan(values)]
    return float(v.mean()) if v.size else float("nan")


def torch_images(pred: Any, target: Any, *, name: str, min_size: int = 1) -> tuple[Any, Any]:
    """Validate a torch image pair (..., C, H, W); uint8 becomes float32 / 255.

    Raises:
        MetricError: one tensor and one array, different shapes, fewer than 3 dimensions, a
            non-float non-uint8 dtype, or images smaller than `min_size`.
    """
    import torch

    if not (is_tensor(pred) and is_tensor(target)):
        raise MetricError(f"{name}: pass two numpy arrays or two torch tensors, not one of each")
    if pred.shape != target.shape:
        raise MetricError(f"{name}: pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.ndim < 3:
        raise MetricError(f"{name}: torch images are (..., C, H, W); got shape {tuple(pred.shape)}")
    out = []
    for a in (pred, target):
        if a.dtype == torch.uint8:
            a = a.to(torch.float32) / 255.0
        elif not a.is_floating_point():
            raise MetricError(f"{name}: images must be uint8 or floating point, got {a.dtype}")
        out.append(a)
    p, t = out
    if t.dtype != p.dtype:
        t = t.to(p.dtype)
    h, w = p.shape[-2], p.shape[-1]
    if h < min_size or w < min_size:
        raise MetricError(f"{name}: images must be at least {min_size}x{min_size} pixels, got {w}x{h}")
    return p, t


def torch_mask(mask: Any, like: Any, lead: tuple[int, ...], hw: tuple[int, int], *, name: str) -> Any:
    """A per-pixel weight mask (..., H, W) as a tensor broadcast to lead + (H, W) (dtype of `like`)."""
    import torch

    if mask is None:
        return None
    m = mask if is_tensor(mask) else torch.as_tensor(np.asarray(mask))
    if m.dtype == torch.bool or not m.is_floating_point():
        m = m.to(like.dtype)
    m = m.to(device=like.device, dtype=like.dtype)
    if not torch.isfinite(m).all() or (m < 0).any():
        raise MetricError(f"{name}: mask weights must be finite and >= 0")
    try:
        return torch.broadcast_to(m, lead + hw)
    except RuntimeError:
        raise MetricError(f"{name}: mask of shape {tuple(m.shape)} does not broadcast to the images' "
                          f"(..., H, W) = {lead + hw}") from None


def reduce_torch(values: Any, reduction: str) -> Any:
    """Per-image tensor -> "none": itself; "mean": 0-d mean over the non-NaN entries."""
    if reduction == "none":
        return values
    keep = ~values.isnan()
    if bool(keep.all()):
        return values.mean()
    return values[keep].mean()
