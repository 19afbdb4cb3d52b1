"""Linear centered kernel alignment (CKA) between two sets of features of the same examples.

- `linear_cka(X, Y)` (Kornblith et al. 2019, google-research `representation_similarity`,
  `feature_space_linear_cka`): with column-centred X (n, p1) and Y (n, p2),
  CKA = ||Y^T X||_F^2 / (||X^T X||_F ||Y^T Y||_F). `debiased=True` uses the unbiased HSIC
  estimator (Song et al. 2012) in the same feature-space form. It is invariant to orthogonal
  transforms and isotropic scaling of either side and to adding a constant to the features:
  CKA(X, X Q) = CKA(X, a X + b) = 1.
- `MinibatchCKA` (Nguyen et al. 2021): for feature sets too large to hold, accumulate the
  unbiased HSIC_1 of each minibatch's linear Gram matrices and report
  sum HSIC_1(K_i, L_i) / sqrt(sum HSIC_1(K_i, K_i) sum HSIC_1(L_i, L_i)).

Everything is computed in float64 numpy (torch tensors are detached and copied to the CPU).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A

__all__ = ["MinibatchCKA", "hsic1", "linear_cka"]


def _features(x: Any, name: str) -> np.ndarray:
    if A.is_tensor(x):
        x = x.detach().float().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2:
        raise A.MetricError(f"{name}: features are (examples, features), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise A.MetricError(f"{name}: features hold NaN or Inf")
    return a


def _pair(x: Any, y: Any, min_rows: int) -> tuple[np.ndarray, np.ndarray]:
    a, b = _features(x, "x"), _features(y, "y")
    if a.shape[0] != b.shape[0]:
        raise A.MetricError(f"CKA compares features of the same examples: {a.shape[0]} rows vs {b.shape[0]}")
    if a.shape[0] < min_rows:
        raise A.MetricError(f"CKA needs at least {min_rows} examples, got {a.shape[0]}")
    return a, b


def _debiased(xty: float, rows_x: np.ndarray, rows_y: np.ndarray, nx: float, ny: float, n: int) -> float:
    # google-research representation_similarity `_debiased_dot_product_similarity_helper`
    return float(xty - n / (n - 2.0) * rows_x.dot(rows_y) + nx * ny / ((n - 1) * (n - 2)))


def linear_cka(x: Any, y: Any, *, debiased: bool = False) -> float:
    """Linear CKA of two feature matrices (n, p1) and (n, p2) over the same n examples.

    Args:
        x, y: numpy arrays or torch tensors, one row per example.
        debiased: use the unbiased HSIC estimator (needs n >= 4).

    Returns:
        CKA in [0, 1] (the debiased value can dip slightly below 0); NaN if one side is constant.

    Raises:
        MetricError: different row counts, too few rows, non-finite values.
    """
    a, b = _pair(x, y, 4 if debiased else 2)
    a = a - a.mean(axis=0, keepdims=True)
    b = b - b.mean(axis=0, keepdims=True)
    xty = float(np.linalg.norm(b.T @ a) ** 2)
    xx = float(np.linalg.norm(a.T @ a))
    yy = float(np.linalg.norm(b.T @ b))
    if debiased:
        n = a.shape[0]
        rx, ry = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
        sx, sy = float(rx.sum()), float(ry.sum())
        xty = _debiased(xty, rx, ry, sx, sy, n)
        xx = float(np.sqrt(max(_debiased(xx**2, rx, rx, sx, sx, n), 0.0)))
        yy = float(np.sqrt(max(_debiased(yy**2, ry, ry, sy, sy, n), 0.0)))
    den = xx * yy
    return xty / den if den > 0 else float("nan")


def hsic1(k: np.ndarray, l: np.ndarray) -> float:  # noqa: E741 - the papers' names
    """Unbiased HSIC_1 (Song et al. 2012) of two (n, n) Gram matrices, n >= 4."""
    n = k.shape[0]
    kt, lt = k.copy(), l.copy()
    np.fill_diagonal(kt, 0.0)
    np.fill_diagonal(lt, 0.0)
    ones_k, ones_l = kt.sum(axis=0), lt.sum(axis=0)
    trace = float(np.einsum("ij,ji->", kt, lt))
    term2 = float(ones_k.sum() * ones_l.sum()) / ((n - 1) * (n - 2))
    term3 = 2.0 / (n - 2) * float(ones_k @ ones_l)
    return (trace + term2 - term3) / (n * (n - 3))


class MinibatchCKA:
    """Linear CKA accumulated over minibatches of paired features (Nguyen et al. 2021).

    Call `update(x, y)` with each minibatch (the same examples on both sides, at least 4 rows),
    then `compute()`. The value does not depend on how the examples were split in expectation;
    with one batch it equals the debiased CKA up to the HSIC normalisation.
    """

    def __init__(self) -> None:
        self._xy = 0.0
        self._xx = 0.0
        self._yy = 0.0
        self.batches = 0

    def update(self, x: Any, y: Any) -> None:
        """Add one minibatch (n >= 4 rows on each side).

        Raises:
            MetricError: different row counts, fewer than 4 rows, non-finite values.
        """
        a, b = _pair(x, y, 4)
        k, l = a @ a.T, b @ b.T  # noqa: E741
        self._xy += hsic1(k, l)
        self._xx += hsic1(k, k)
        self._yy += hsic1(l, l)
        self.batches += 1

    def compute(self) -> float:
        """The accumulated CKA (NaN before any update or when one side is constant)."""
        den = np.sqrt(self._xx * self._yy) if self._xx > 0 and self._yy > 0 else 0.0
        return float(self._xy / den) if den > 0 else float("nan")
