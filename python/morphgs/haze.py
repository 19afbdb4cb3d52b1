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
- each at c_t + r u: t a uniformly drawn training camera, u a uniform direction, r log-uniform
  in [R_LO, R_HI] D (0.3-0.6);
- kept only where, with 3 or more training cameras, camera t does not see it (it sits beside or
  behind it), at least 2 others do, and every training view that sees it sees it at most
  MAX_PX (30) pixels wide (3 sigma of its largest scale); with 2 cameras, where the other one
  sees it (that wide at most); candidates are drawn in rounds until n are kept (at most 40
  rounds: a path that leaves no such place gets fewer, none at worst);
- largest scale D x SCALE x e^(0.45 z) (SCALE 0.05), the middle one smaller by e^(0.95 |z|),
  the smallest smaller than the middle by e^(2.3 |z|), a uniformly random rotation;
- opacity OPACITY x e^(0.85 z) (OPACITY 0.10), clipped to [0.01, 0.9]; colour 0.76 + 0.2 z +
  0.08 z_c per channel (z shared, z_c per channel), no view dependence (higher SH bands zero).

Every draw comes from one NumPy generator seeded by (seed, 17), and the draws depend only on
the cameras, the seed and v: the same bytes for any thread count and any scene (tests/test_haze.py
pins them). Not yet for any CPU: NumPy's vectorised exp / log / reductions follow the CPU's SIMD
level (measured with NPY_DISABLE_CPU_FEATURES: the pinned digest is the same with NumPy's AVX-512
paths off, AVX2 on, and changes with AVX2 off too, SSE only), which the Rust kernel's ops do not;
moving the op there is what pins it everywhere. The op changes no Gaussian of the scene: it appends.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["MAX_PX", "OPACITY", "PER_VIEW", "R_HI", "R_LO", "SCALE", "haze_gaussians", "spacing"]

PER_VIEW = 250.0
R_LO, R_HI = 0.3, 0.6
SCALE = 0.05
OPACITY = 0.10
MAX_PX = 30.0
_LUMINANCE, _LUMINANCE_SD, _CHROMA_SD = 0.76, 0.2, 0.08
_FLAT_MID, _FLAT_MIN = 0.95, 2.3  # half-normal sds of ln(largest / middle) and ln(middle / smallest)
_ROUNDS = 40
_OP_ID = 17  # after shatter's 16: the seed stream of this op
_SH_C0 = 0.28209479177387814


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
    `K` (V, 3, 3), one image size): arrays means (n, 3), quats (n, 4, wxyz), log_scales (n, 3),
    opacity_logits (n,), sh0 (n, 3), all float32 (n may be 0)."""
    w2c = np.asarray(world_to_camera, np.float64)
    K = np.asarray(K, np.float64)
    nv = len(w2c)
    if w2c.shape != (nv, 4, 4) or K.shape != (nv, 3, 3):
        raise ValueError(f"haze: world_to_camera must be (V, 4, 4) and K (V, 3, 3), got {w2c.shape} and {K.shape}")
    value = float(value)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"haze: the value must be finite and >= 0, got {value}")
    centers = np.linalg.inv(w2c)[:, :3, 3]
    D = spacing(centers)
    n = int(round(value * PER_VIEW * nv)) if D > 0 else 0
    rng = np.random.default_rng([int(seed) & (2**64 - 1), _OP_ID])
    need = min(2, nv - 1)
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    found = 0
    for _ in range(_ROUNDS if n else 0):
        m = 4 * n
        t = rng.integers(0, nv, m)
        u = rng.normal(size=(m, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        r = D * np.exp(rng.uniform(np.log(R_LO), np.log(R_HI), m))
        p = centers[t] + u * r[:, None]
        smax = D * SCALE * np.exp(0.45 * rng.normal(size=m))
        pc = np.einsum("vij,mj->mvi", w2c[:, :3, :3], p) + w2c[None, :, :3, 3]
        z = pc[..., 2]
        zs = np.maximum(z, 1e-12)
        x = K[None, :, 0, 0] * pc[..., 0] / zs + K[None, :, 0, 2]
        y = K[None, :, 1, 1] * pc[..., 1] / zs + K[None, :, 1, 2]
        sees = (z > 0.05 * D) & (x >= 0) & (x < width) & (y >= 0) & (y < height)
        wide = K[None, :, 0, 0] * 3.0 * smax[:, None] / zs
        ok = (sees.sum(axis=1) >= need) & np.all(~sees | (wide <= MAX_PX), axis=1)
        if nv >= 3:
            ok &= ~sees[np.arange(m), t]
        kept.append((p[ok], smax[ok]))
        found += int(ok.sum())
        if found >= n:
            break
    p = np.concatenate([k[0] for k in kept])[:n] if kept else np.zeros((0, 3))
    smax = np.concatenate([k[1] for k in kept])[:n] if kept else np.zeros(0)
    k = len(p)
    mid = smax * np.exp(-_FLAT_MID * np.abs(rng.normal(size=k)))
    scales = np.stack([smax, mid, mid * np.exp(-_FLAT_MIN * np.abs(rng.normal(size=k)))], axis=1)
    q = rng.normal(size=(k, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    opacity = np.clip(OPACITY * np.exp(0.85 * rng.normal(size=k)), 0.01, 0.9)
    colour = _LUMINANCE + _LUMINANCE_SD * rng.normal(size=(k, 1)) + _CHROMA_SD * rng.normal(size=(k, 3))
    return {"means": p.astype(np.float32), "quats": q.astype(np.float32),
            "log_scales": np.log(scales).astype(np.float32),
            "opacity_logits": np.log(opacity / (1.0 - opacity)).astype(np.float32),
            "sh0": ((colour - 0.5) / _SH_C0).astype(np.float32)}
