"""The `veil` op (docs/artifacts.md, "Veil"): faint, wide Gaussians a sparse fit places where every
training view that sees them shows their own colour.

A real object capture's sparse fit explains its photos' backdrop with large, faint splats of the
backdrop's colour at the object's depth, beside its silhouette: dark on dark in every training
view, so nothing in the fit corrects them, and from the views between they slide over the object
and darken it. Measured on the committed `skull` capture (`benches/capture_anatomy.py`,
docs/artifacts.md): 93-97 % of the held-out error on the object and 76-98 % of it darker than the
dense fit, dark Gaussians holding 67-80 % of the area near the object's depth (44-47 % in the
dense fit), and at 8 photos a veil of 125 dark (luminance median 0.04), wide (footprint median
9 px), faint (opacity median 0.14) Gaussians in front of the object. The ambiguity that lets them
stay is photometric: no training view can tell them from the surface they cover.

`veil` adds such Gaussians to a clean scene, without a fit. At value v (strength x base), with V
virtual training cameras (V >= 2) and their clean renders (colour and expected depth):

- at most n = round(v x PER_VIEW x V) Gaussians (PER_VIEW 100);
- candidate i (0, 1, 2, ...) takes a uniformly drawn training camera t and pixel of it (its colour
  is that pixel's clean colour), a depth on that pixel's ray: the clean depth of another uniformly
  drawn pixel of view t (where something is hit: the depths the scene's content has in that view),
  brought forward by e^(-FRONT u) (FRONT 0.3, u uniform), and a footprint sigma in view t
  log-uniform in [SIGMA_PX_LO, SIGMA_PX_HI] = [2, 24] pixels;
- it is kept when it lies in front of what its pixel shows, at least MIN_VIEWS (2) training views
  see it (in their image and not more than HIDDEN = 1.1 x their clean depth behind the surface),
  none sees it wider than MAX_SIGMA_PX (48 pixels of sigma), and in every one that sees it the nine
  pixels at its centre and two sigma around it are within TOLERANCE (0.08 RMS over the channels)
  of its colour; the first n kept candidates, in index order, are the veil (at most 400 n are
  judged: a scene with no uniform regions gets fewer, none at worst);
- each axis' log scale is ln sigma + 0.35 z, a uniformly random rotation, opacity OPACITY x
  e^(0.8 z) (OPACITY 0.15) clipped to [0.02, 0.9], no view dependence.

So the training views stay right to within the tolerance wherever the veil lies, and the views
between them see it where the training views do not agree: over the object. The op runs in the
Rust kernel (`splat_core::perturb::veil`, which holds the constants): every draw of candidate i
from its own counter-based stream (seed, op 18, i), candidates judged in parallel chunks and kept
in index order, only exactly rounded operations and the crate's own exp and ln, so the bytes are
the same for any thread count and CPU, and a larger value keeps the same first Gaussians and adds
more. The op changes no Gaussian of the scene: it appends.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["FRONT", "MAX_SIGMA_PX", "MAX_VALUE", "MIN_VIEWS", "OPACITY", "PER_VIEW", "SIGMA_PX_HI", "SIGMA_PX_LO",
           "TOLERANCE", "veil_gaussians"]

# the kernel's constants (splat_core::perturb::veil), for tests and benches
MAX_VALUE = 16.0  # the largest value (the strength parameterisation's limit)
PER_VIEW = 100.0
TOLERANCE = 0.08
FRONT = 0.3
SIGMA_PX_LO, SIGMA_PX_HI = 2.0, 24.0
MAX_SIGMA_PX = 48.0
MIN_VIEWS = 2
OPACITY = 0.15


def veil_gaussians(value: float, world_to_camera: Any, K: Any, images: Any, depth: Any,
                   seed: int) -> dict[str, np.ndarray]:
    """The veil Gaussians of value `value` for the training cameras (`world_to_camera` (V, 4, 4),
    `K` (V, 3, 3)) and their clean renders (`images` (V, H, W, 3) in [0, 1], `depth` (V, H, W), the
    expected camera z, 0 where nothing is hit): arrays means (n, 3), quats (n, 4, wxyz),
    log_scales (n, 3), opacity_logits (n,), sh0 (n, 3), all float32 (n may be 0).

    Raises:
        ValueError: a value that is not finite and in [0, MAX_VALUE] (16), fewer than two cameras
            (a veil Gaussian must agree with two training views), bad matrices or maps that do not
            match them.
    """
    from morphgs import _core

    w2c = np.ascontiguousarray(world_to_camera, np.float64)
    K = np.ascontiguousarray(K, np.float64)
    if w2c.ndim != 3 or w2c.shape[1:] != (4, 4) or K.shape != (len(w2c), 3, 3):
        raise ValueError(f"veil: world_to_camera must be (V, 4, 4) and K (V, 3, 3), got {w2c.shape} and {K.shape}")
    value = float(value)
    if not np.isfinite(value) or not 0 <= value <= MAX_VALUE:
        raise ValueError(f"veil: the value must be finite and in [0, {MAX_VALUE:g}], got {value}")
    return dict(_core._veil(w2c, K, np.ascontiguousarray(images, np.float32), np.ascontiguousarray(depth, np.float32),
                            value=value, seed=int(seed)))
