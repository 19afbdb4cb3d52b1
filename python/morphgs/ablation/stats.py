"""Small pure statistics of the report: mean with a 95 % t confidence interval, and a paired
sign-flip permutation test (exact up to 16 pairs, else 20 000 seeded random flips)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["mean_ci", "paired_permutation_p"]

# two-sided 95 % Student t quantiles for 1..30 degrees of freedom (then the normal 1.96)
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145,
         2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048,
         2.045, 2.042)


def mean_ci(values: Sequence[float]) -> tuple[float, float, int]:
    """(mean, half-width of the 95 % CI, n) of the finite values; the half-width is NaN for n < 2
    and the mean NaN for n = 0 (an infinite value, e.g. PSNR of identical clips, makes the mean inf)."""
    a = np.asarray([v for v in values if v is not None and not math.isnan(v)], np.float64)
    n = len(a)
    if n == 0:
        return math.nan, math.nan, 0
    m = float(a.mean())
    if n < 2 or not np.isfinite(a).all():
        return m, math.nan, n
    t = _T975[n - 2] if n - 1 <= len(_T975) else 1.96
    return m, float(t * a.std(ddof=1) / math.sqrt(n)), n


def paired_permutation_p(a: Sequence[float], b: Sequence[float], *, seed: int = 0) -> float:
    """Two-sided p of the mean paired difference a - b under random sign flips (NaN if < 2 pairs
    or any value is not finite)."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if len(d) < 2 or not np.isfinite(d).all():
        return math.nan
    obs = abs(d.mean())
    n = len(d)
    if n <= 16:
        signs = ((np.arange(2**n)[:, None] >> np.arange(n)) & 1) * 2 - 1
    else:
        signs = np.random.default_rng(seed).choice([-1, 1], size=(20000, n))
    null = np.abs((signs * d).mean(axis=1))
    return float(np.mean(null >= obs - 1e-12))
