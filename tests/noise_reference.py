"""A NumPy reference of the counter generator's normal draws (crates/splat-core/src/rng.rs), for
tests: the kernel draws in float32 polynomials, this in float64 (they agree to about 1e-6)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from morphgs.noise import _words


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
