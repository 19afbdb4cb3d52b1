"""The `haze` op (docs/artifacts.md, "Haze"): the faint, large Gaussians a sparse fit leaves
beside its cameras.

A 3DGS fit from a few views starts from points along the training rays, some of them close to
the cameras. Those that no training view needs are faded but not removed, and the ones that sit
beside a training camera, outside its own view, are seen small and faint by the other training
views: nothing corrects them. A novel camera on the same path passes right by them and sees them
tens of pixels wide: the milky haze and streaks that make most of a sparse fit's error between
its training views. Measured on the toy study's nine real sparse fits (three rooms at S18 / S20 /
S24, 60k Gaussians each; `benches/haze_anatomy.py`, docs/artifacts.md): 2,500-3,000
Gaussians (about 5 %) within half a training-camera spacing D of the capture path and wider than
0.03 D hold most of the error: without them the novel-view clips go from 11.3-16.9 dB to
18.7-20.8 dB at S18 / S20, and the training views barely change. Their statistics, the same in
every scene and regime: distance to the nearest training camera 0.33-0.53 D (quartiles), largest
scale 0.04-0.08 D (median 0.05 D), flattened more than stretched (ln(largest / middle scale)
half-normal of sd 0.95, ln(middle / smallest) half-normal of sd 2.3, independent: soft sheets,
not needles), opacity 0.06-0.19 (median 0.10), colour bright and near grey (luminance 0.76, sd
0.2). (A real capture's sparse fits, the committed `skull`'s, hold almost none of them: the
population is the built-in rooms' failure, measured there; docs/artifacts.md.)

`haze` adds such Gaussians to a clean scene, without a fit. At value v (strength x base), with
V virtual training cameras (centres c_t) and D the median distance from each to its nearest:

- n = round(v x PER_VIEW x V) Gaussians (PER_VIEW 250: v = 1 gives the measured population);
- candidate i (0, 1, 2, ...) sits at c_t + r u: t a uniformly drawn training camera, u a uniform
  direction, r log-uniform in [R_LO, R_HI] D (0.3-0.6);
- it is kept only where, with 3 or more training cameras, camera t does not see it (it sits
  beside or behind it), at least 2 others do, and every training view that sees it sees it at
  most MAX_PX (30) pixels wide (3 sigma of its largest scale); with 2 cameras, where the other
  one sees it (that wide at most); the first n kept candidates, in index order, are the haze (at
  most 160 n candidates are judged: a path that leaves no such place gets fewer, none at worst);
- largest scale D x SCALE x e^(0.45 z) (SCALE 0.05), the middle one smaller by e^(0.95 |z|),
  the smallest smaller than the middle by e^(2.3 |z|), a uniformly random rotation;
- opacity OPACITY x e^(0.85 z) (OPACITY 0.10), clipped to [0.01, 0.9]; colour 0.76 + 0.2 z +
  0.08 z_c per channel (z shared, z_c per channel), no view dependence (higher SH bands zero).

The op runs in the Rust kernel (`splat_core::perturb::haze`, which holds the constants): every
draw of candidate i from its own counter-based stream (seed, op 17, i), candidates judged in
parallel chunks and kept in index order, only exactly rounded operations and the crate's own exp
and ln, so the bytes are the same for any thread count and CPU, and a larger value keeps the same
first Gaussians and adds more. The op changes no Gaussian of the scene: it appends. (Its first two
versions were NumPy, their bytes following NumPy's SIMD level; docs/artifacts.md.)
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["MAX_PX", "MAX_VALUE", "OPACITY", "PER_VIEW", "R_HI", "R_LO", "SCALE", "haze_gaussians", "spacing"]

# the kernel's constants (splat_core::perturb::haze), for tests and benches
MAX_VALUE = 16.0  # the largest value (the strength parameterisation's limit)
PER_VIEW = 250.0
R_LO, R_HI = 0.3, 0.6
SCALE = 0.05
OPACITY = 0.10
MAX_PX = 30.0


def spacing(centers: np.ndarray) -> float:
    """D: the median distance from each camera centre to its nearest other (0 for one camera)."""
    c = np.asarray(centers, np.float64)
    if len(c) < 2:
        return 0.0
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def haze_gaussians(value: float, world_to_camera: Any, K: Any, width: int, height: int,
                   seed: int) -> dict[str, np.ndarray]:
    """The haze Gaussians of value `value` for the training cameras (`world_to_camera` (V, 4, 4),
    `K` (V, 3, 3), V >= 2, one image size): arrays means (n, 3), quats (n, 4, wxyz), log_scales
    (n, 3, largest first), opacity_logits (n,), sh0 (n, 3), all float32 (n may be 0).

    Raises:
        ValueError: a value that is not finite and in [0, MAX_VALUE] (16), fewer than two cameras, bad matrices.
    """
    from morphgs import _core

    w2c = np.ascontiguousarray(world_to_camera, np.float64)
    K = np.ascontiguousarray(K, np.float64)
    if w2c.ndim != 3 or w2c.shape[1:] != (4, 4) or K.shape != (len(w2c), 3, 3):
        raise ValueError(f"haze: world_to_camera must be (V, 4, 4) and K (V, 3, 3), got {w2c.shape} and {K.shape}")
    value = float(value)
    if not np.isfinite(value) or not 0 <= value <= MAX_VALUE:
        raise ValueError(f"haze: the value must be finite and in [0, {MAX_VALUE:g}], got {value}")
    return dict(_core._haze(w2c, K, int(width), int(height), value=value, seed=int(seed)))
