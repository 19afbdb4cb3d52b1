"""Colour shift: how far a refined frame's overall colour has moved from the target's.

Video refiners shift colour on pass-through and the tint can grow along a clip (users report it
for Wan/VACE and Difix); PSNR mixes that with structure and SSIM mostly ignores it. This metric
isolates it.

Definition (per frame): convert both frames to CIELAB (sRGB, D65; `morphgs.color.rgb_to_lab`),
average L*, a*, b* over the frame's pixels (or the masked ones), and take the CIE76 colour
difference of the two means:

    color_shift = || mean_Lab(pred) - mean_Lab(target) ||_2      (Delta E*ab; about 2.3 is a
                                                                  just-noticeable difference)

`color_shift_components` gives the signed mean offsets (dL*, da*, db*) per frame, to tell a
brightness change from a tint (da* > 0 is towards red, db* > 0 towards yellow). Reinhard
transfer (`morphgs.color.reinhard_transfer`) against the target makes the shift about 0 by
construction, which is why it is measured before any colour correction against the target.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A

__all__ = ["color_shift", "color_shift_components"]


def _to_numpy(x: Any) -> Any:
    if A.is_tensor(x):  # (..., C, H, W) torch -> (..., H, W, C) numpy; not differentiable
        return x.detach().cpu().movedim(-3, -1).numpy()
    return x


def color_shift_components(pred: Any, target: Any, *, mask: Any = None) -> np.ndarray:
    """Signed per-image offsets of the mean CIELAB colour, pred minus target.

    Args:
        pred, target: RGB images, numpy (..., H, W, 3) (uint8, or floats in [0, 1]) or torch
            (..., 3, H, W); the same shape.
        mask: optional per-pixel weights (..., H, W); a weighted mean over them.

    Returns:
        (..., 3) float64 array of (dL*, da*, db*); NaN for an image whose mask is empty.

    Raises:
        MetricError: mismatched shapes, not 3 channels, a bad mask.
    """
    from morphgs.color import rgb_to_lab

    p, t = A.numpy_images(_to_numpy(pred), _to_numpy(target), name="color_shift")
    lead, (h, w, c) = p.shape[:-3], p.shape[-3:]
    if c != 3:
        raise A.MetricError(f"color_shift: images must have 3 channels (RGB), got {c}")
    m = A.numpy_mask(_to_numpy(mask), lead, (h, w), name="color_shift")
    n = math.prod(lead)
    p, t = p.reshape(n, h, w, 3), t.reshape(n, h, w, 3)
    m = None if m is None else m.reshape(n, h * w).astype(np.float64)
    out = np.empty((n, 3))
    for i in range(n):  # one frame at a time: the Lab temporaries stay frame-sized
        lp = rgb_to_lab(p[i]).reshape(-1, 3)  # uint8 via a table; float64 stays float64
        lt = rgb_to_lab(t[i]).reshape(-1, 3)
        d = lp.astype(np.float64) - lt.astype(np.float64)
        if m is None:
            out[i] = d.mean(axis=0)
        else:
            wsum = m[i].sum()
            out[i] = m[i] @ d / wsum if wsum > 0 else np.nan
    return out.reshape(*lead, 3)


def color_shift(pred: Any, target: Any, *, mask: Any = None, reduction: str = "mean") -> Any:
    """CIE76 Delta E*ab between the mean CIELAB colours of pred and target, per image.

    Lower is better; 0 when the mean colours agree (structure is not compared). See the module
    docstring for the definition.

    Args:
        pred, target: as `color_shift_components`.
        mask: optional per-pixel weights (..., H, W).
        reduction: "mean" (over images, NaN images skipped) or "none" (shape (...,)).

    Returns:
        A float ("mean") or a float64 array (...,) ("none"). Torch inputs are read as numpy
        (no gradient).
    """
    A.check_reduction(reduction)
    comp = color_shift_components(pred, target, mask=mask)
    return A.reduce_numpy(np.sqrt((comp**2).sum(axis=-1)), reduction)
