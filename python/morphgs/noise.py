"""morphgs' counter-based generator (docs/perturbation.md, "Determinism"), vectorised in NumPy.

The Rust kernel (`crates/splat-core/src/rng.rs`) draws the noise of the six SPEC §2 operations;
this module draws the same streams for the operations done in Python (the strength
parameterisation's log-scale and rotation-angle noise, op ids 7 and 8): draw j of Gaussian i in
op k is a pure function of (seed, k, i, j), so the result does not depend on the thread count,
on the other operations or on the other Gaussians. The integer part (SplitMix64 words) is exactly
the kernel's; the Box-Muller step is computed in float64 here (the kernel's float32 polynomials
agree to about 1e-6 relative). NumPy's float64 log/sin/cos are single-threaded elementwise, so
the draws are the same for any thread count; across CPUs they may differ in the last float64
bits (NumPy picks SIMD implementations at run time), which changes a float32 result only when it
lies within a few float64 ulps of a float32 rounding boundary (about 1 draw in 10^7).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["OP_LOG_SCALE", "OP_ROTATION_ANGLE", "normals", "uniforms"]

#: Op ids of the strength parameterisation's own noise (1 to 6 are the kernel's, SPEC §2).
OP_LOG_SCALE = 7
OP_ROTATION_ANGLE = 8

_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_SALT = np.uint64(0x6D6F727068677321)  # "morphgs!"
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix64(z: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))  # type: ignore[no-any-return]


def _key(seed: int, op: int) -> np.uint64:
    with np.errstate(over="ignore"):
        s = _mix64(np.array([seed], dtype=np.uint64) ^ _SALT)
        return _mix64(s + np.uint64(op) * _GAMMA)[0]  # type: ignore[no-any-return]


def _words(seed: int, op: int, index: npt.ArrayLike, w: int) -> npt.NDArray[np.uint64]:
    idx = np.asarray(index, dtype=np.uint64)
    with np.errstate(over="ignore"):
        base = _mix64(idx ^ _key(seed, op))
        return _mix64(base + np.uint64(w + 1) * _GAMMA)


def normals(seed: int, op: int, index: npt.ArrayLike, draws: int) -> npt.NDArray[np.float64]:
    """Standard normal draws 0..draws-1 of the Gaussians `index` in op `op`: shape (len, draws).

    Box-Muller on word j // 2 of each Gaussian's stream: u1 from the high 32 bits, the angle
    from the low 32 bits; even j the cosine branch, odd j the sine branch (rng.rs).
    """
    idx = np.asarray(index, dtype=np.uint64).reshape(-1)
    out = np.empty((idx.size, draws), dtype=np.float64)
    for w in range((draws + 1) // 2):
        word = _words(seed, op, idx, w)
        hi = (word >> np.uint64(32)).astype(np.uint32)
        lo = (word & np.uint64(0xFFFFFFFF)).astype(np.uint32)
        u1 = ((hi >> np.uint32(1)) | np.uint32(1)).astype(np.float64) * 2.0**-31
        r = np.sqrt(-2.0 * np.log(u1))
        quadrant = (lo >> np.uint32(30)).astype(np.float64)
        frac = ((lo >> np.uint32(6)) & np.uint32(0xFFFFFF)).astype(np.float64) * 2.0**-24
        angle = (quadrant + frac) * (np.pi / 2.0)
        out[:, 2 * w] = r * np.cos(angle)
        if 2 * w + 1 < draws:
            out[:, 2 * w + 1] = r * np.sin(angle)
    return out


def uniforms(seed: int, op: int, index: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The uniform in [0, 1) of each Gaussian `index` in op `op` (top 24 bits of word 0)."""
    word = _words(seed, op, index, 0)
    return (word >> np.uint64(40)).astype(np.float64) * 2.0**-24
