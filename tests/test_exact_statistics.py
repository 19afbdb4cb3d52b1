"""The two statistics taken from SciPy are the exact ones: the ablation report's 95 % interval is
Student's t interval for every n (it was a 3-decimal t table up to 30 degrees of freedom, then
1.96), and calibration's W1 is the exact distance between empirical distributions (it was the
mean difference of 101 interpolated quantiles)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from morphgs.ablation.stats import mean_ci
from morphgs.calibration.goodness import distances, w1

scipy_stats = pytest.importorskip("scipy.stats")


@pytest.mark.parametrize("n", [2, 3, 5, 31, 32, 40])
def test_mean_ci_is_scipys_t_interval(n: int) -> None:
    values = np.random.default_rng(n).normal(3.0, 2.0, n)
    m, half, count = mean_ci(values.tolist())
    lo, hi = scipy_stats.t.interval(0.95, n - 1, loc=values.mean(), scale=scipy_stats.sem(values))
    assert count == n and m == pytest.approx(values.mean())
    assert (m - half, m + half) == pytest.approx((lo, hi), rel=1e-12)


def _brute_w1(a: np.ndarray, b: np.ndarray) -> float:
    """W1 of two empirical distributions by definition: repeat each sample up to the lcm of the
    sizes (equal weights), sort, and average the absolute differences of matched points."""
    k = math.lcm(len(a), len(b))
    return float(np.mean(np.abs(np.sort(np.repeat(a, k // len(a))) - np.sort(np.repeat(b, k // len(b))))))


@pytest.mark.parametrize(("na", "nb", "seed"), [(1, 1, 0), (2, 3, 1), (4, 4, 2), (3, 5, 3), (7, 2, 4), (6, 4, 5)])
def test_w1_is_the_exact_distance(na: int, nb: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    a, b = rng.normal(0.0, 1.0, na), rng.gamma(2.0, 1.0, nb)
    a[: na // 2] = np.round(a[: na // 2])  # ties too
    assert w1(a, b) == pytest.approx(_brute_w1(a, b), rel=1e-12, abs=1e-15)
    assert w1(a, a) == 0.0 and w1(a, b) == pytest.approx(w1(b, a), rel=1e-12)


def test_w1_of_few_pairs_is_not_the_old_quantile_approximation() -> None:
    # the old distance interpolated linearly between order statistics: for {0, 1} against {0.5} it
    # said 0.25, where half the mass moves 0.5 each way (W1 = 0.5); with 3 against 2 values 0.95
    # where it is 7/6
    q = np.linspace(0.0, 1.0, 101)

    def old(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.mean(np.abs(np.quantile(a, q) - np.quantile(b, q))))

    a, b = np.array([0.0, 1.0]), np.array([0.5])
    assert old(a, b) == pytest.approx(0.2525, abs=1e-4) and w1(a, b) == pytest.approx(0.5)
    a, b = np.array([0.0, 0.0, 3.0]), np.array([1.0, 2.0])
    assert old(a, b) == pytest.approx(0.9505, abs=1e-4) and w1(a, b) == pytest.approx(7 / 6) == _brute_w1(a, b)
    # distances() divides by the real values' IQR (here 1.5)
    real = np.array([[0.0], [1.0], [2.0], [3.0]])
    assert distances(real, real + 0.5, ["x"]) == {"x": pytest.approx(0.5 / 1.5)}
