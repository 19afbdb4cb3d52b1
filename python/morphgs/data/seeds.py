"""Sample seeds: every random choice of a training sample (its temporal offset, crop, flip, and
for live pairs the scene, cameras and perturbation) comes from one 63-bit seed that is a pure
function of (run seed, epoch, sample index) — not of the worker, the rank or the order in which
samples are drawn, so resumed and distributed runs see the same samples as a single process.

    seed = uint64_le(sha256("morphgs/sample/v1\\0{run_seed}\\0{epoch}\\0{index}")[:8]) >> 1

(the same construction as curation's pair seeds, docs/curation.md). NumPy and hashlib only.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["epoch_permutation", "rng", "sample_seed"]


def _u63(text: str) -> int:
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1


def sample_seed(run_seed: int, epoch: int, index: int) -> int:
    """The seed of sample `index` of `epoch` in a run seeded `run_seed` (0 <= seed < 2**63)."""
    return _u63(f"morphgs/sample/v1\0{int(run_seed)}\0{int(epoch)}\0{int(index)}")


def rng(seed: int) -> np.random.Generator:
    """The NumPy generator a sample draws its random choices from."""
    return np.random.Generator(np.random.PCG64(int(seed)))


def epoch_permutation(n: int, run_seed: int, epoch: int) -> np.ndarray:
    """The order in which an epoch visits n pairs (a pure function of the run seed and epoch)."""
    return rng(_u63(f"morphgs/epoch-order/v1\0{int(run_seed)}\0{int(epoch)}")).permutation(n)
