"""Small pure statistics of the report: mean with a 95 % t confidence interval, and a paired
sign-flip permutation test (exact up to 16 pairs, else 20 000 seeded random flips)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["mean_ci", "paired_permutation_p"]

def mean_ci(values: Sequence[float]) -> tuple[float, float, int]:
    """(mean, half-width of the 95 % CI, n) of the finite values: Student's t interval,
    `scipy.stats.t.ppf(0.975, n - 1)` standard errors. The half-width is NaN for n < 2 and the
    mean NaN for n = 0 (an infinite value, e.g. PSNR of identical clips, makes the mean inf)."""
    a = np.asarray([v for v in values if v is not None and not math.isnan(v)], np.float64)
    n = len(a)
    if n == 0:
        return math.nan, math.nan, 0
    m = float(a.mean())
    if n < 2 or not np.isfinite(a).all():
        return m, math.nan, n
    try:
        from scipy.stats import t
    except ImportError as e:  # pragma: no cover - metrics extra missing
        raise ImportError("the report's confidence intervals need SciPy: pip install 'morphgs[metrics]'") from e
    return m, float(t.ppf(0.975, n - 1) * a.std(ddof=1) / math.sqrt(n)), n


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
