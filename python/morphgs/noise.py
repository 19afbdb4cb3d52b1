"""The uniforms of morphgs' counter-based generator (docs/perturbation.md, "Determinism") in NumPy.

The Rust kernel (`crates/splat-core/src/rng.rs`) draws all the perturbation noise, the strength
parameterisation's log-scale and rotation-angle noise (op ids 7 and 8) included. This module
draws the one value made in Python: a pair's strength draw from a strength distribution (op id
9, `morphgs.strength.draw_strength`), the uniform of index 0 of the seed's stream. It uses integer
arithmetic (the kernel's SplitMix64 words) and one exact conversion (a 24-bit integer times
2^-24), so it is the same bits as the kernel's `rng::uniform` on every CPU.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["OP_LOG_SCALE", "OP_ROTATION_ANGLE", "OP_STRENGTH_DRAW", "uniforms"]

#: Op ids of the strength parameterisation's own noise (1 to 6 are the kernel's, SPEC §2).
OP_LOG_SCALE = 7
OP_ROTATION_ANGLE = 8
#: Op id of a pair's strength draw from a strength distribution.
OP_STRENGTH_DRAW = 9

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


def uniforms(seed: int, op: int, index: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The uniform in [0, 1) of each Gaussian `index` in op `op` (top 24 bits of word 0)."""
    word = _words(seed, op, index, 0)
    return (word >> np.uint64(40)).astype(np.float64) * 2.0**-24
