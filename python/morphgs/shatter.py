"""The `shatter` op (docs/artifacts.md): what a fit from a few views is made of.

A 3DGS fit from K views starts from points spread along the training rays and can only learn what
those views see: it reproduces each training pixel with whatever Gaussians lie on its ray, at
whatever depth they started. Seen from a training view the result is right; seen from between
them, the surfaces break into confetti of small splats at the wrong depths, coloured like the
pixels they were fitted to (docs/artifacts.md shows a built-in room fitted from 5 of 96 views).

`shatter` builds that directly, without a fit. At value v (strength x base):

- each Gaussian of the scene is removed with probability p = 1 - exp(-v);
- each pixel of each virtual training view (alpha > 0.5 in its clean render, a positive depth) spawns, with
  probability q = min(p, BUDGET x the removals / (PER_PIXEL x the valid pixels)), PER_PIXEL (3)
  fragments: small isotropic Gaussians on that pixel's ray (each at a uniform point within the
  pixel) at depth d' = d exp(sigma z), z ~ N(0, 1), sigma = DEPTH_SPREAD v (0.3 v), clipped to
  [d / c, c d], c = max(4, e^sigma) (a factor 4 up to v = 4.6, one sigma beyond, so sparser
  regimes stay within reach), where d is the clean render's depth there; a log-normal footprint of median
  FOOTPRINT_PX (0.5) pixel in that view; opacities that stack to the pixel's alpha;
- each fragment's colour is view-dependent (SH up to band 1), fitted by least squares to its
  own pixel (weight 4) and to the pixel of every other training view whose frustum holds it, as a
  fit makes its splats match every training view they can (a ridge of 1.0 keeps band 1 small
  where the views disagree);
- where that cannot work (a colour error above MAX_ERROR, 0.08 RMS, about 20/255, in one of those
  views, or a splat another training view would see wider than MAX_FOOTPRINT_PX, 3 pixels,
  sigma), the fragment is dropped (a fit makes what it cannot reconcile transparent), or, with
  `drop=False`, put back onto the surface with its pixel's colour.

The constants were set from a real sparse:20 fit of a built-in room (docs/artifacts.md, "What a
sparse fit is made of"; `benches/sparse_anatomy.py`): with them the pairs' error spectrum is
within 0.6 dB of the real pairs' in every band. At small v a few Gaussians are replaced by
fragments close to the surface; as v grows, every Gaussian goes and the fragments spread along
their rays, as a sparse fit's do. What still differs: a real fit's training views are right
(48-51 dB), shatter's are not (12-17 dB).

The op runs in the Rust kernel (`splat_core::perturb::shatter`, which holds the constants): every
draw keyed by (seed, op 16, a Gaussian's or a training pixel's index), each fragment computed
from its own draws in parallel, so the bytes are the same for any thread count and CPU. (Until
2026-11-28 it was NumPy, 10x slower; its pairs are statistically the same, their bytes are not.)
"""

from __future__ import annotations

import numpy as np

__all__ = ["OP_ID", "fragments", "removal"]

#: The op's id in the seed (after the Rust kernel's 10-14 and popping's 15).
OP_ID = 16
#: Fragments per spawning pixel (the Rust kernel's constant, for the docs and the fragment budget).
PER_PIXEL = 3
#: At most this many fragments per removed Gaussian.
BUDGET = 4
#: The default largest RMS colour error a kept fragment may have in a training view that sees it.
MAX_ERROR = 0.08


def removal(n: int, value: float, seed: int) -> np.ndarray:
    """Which of n Gaussians `shatter` removes at `value` (bool (n,)): the same uniforms at every
    value, so a larger value removes a superset."""
    from morphgs._core import _shatter_removal

    return _shatter_removal(int(n), value=float(value), seed=int(seed))


def fragments(value: float, images: np.ndarray, depth: np.ndarray, alpha: np.ndarray, world_to_camera: np.ndarray,
              K: np.ndarray, removed: int, seed: int, ridge: float = 1.0, max_error: float | None = None,
              drop: bool = True) -> dict[str, np.ndarray]:
    """The fragments of the training views (module doc) as arrays of a GaussianScene (means,
    quats, log_scales, opacity_logits, sh0, and sh1: the band-1 SH coefficients (N, 3, 3)), float32,
    and view: the training view each was spawned from (N,) int32.

    Args:
        value: the op's value v >= 0. images (T, H, W, 3), depth (T, H, W), alpha (T, H, W): the
            clean renders of the T training views. world_to_camera (T, 4, 4), K (T, 3, 3).
        removed: how many Gaussians were removed (the fragment budget is BUDGET times that).
        ridge, max_error, drop: the colour fit's band-1 ridge, the largest RMS colour error a kept
            fragment may have in a view it is fitted to, and whether one that fails is dropped
            (else put back on the surface with its pixel's colour).

    Raises:
        ValueError: a bad parameter, or maps and cameras that do not match (named).
    """
    from morphgs._core import _shatter

    rgb, dep, alp = (np.ascontiguousarray(a, np.float32) for a in (images, depth, alpha))
    w2c, k = (np.ascontiguousarray(a, np.float64) for a in (world_to_camera, K))
    return _shatter(float(value), rgb, dep, alp, w2c, k, int(removed), seed=int(seed), ridge=float(ridge),
                    max_error=MAX_ERROR if max_error is None else float(max_error), drop=bool(drop))
