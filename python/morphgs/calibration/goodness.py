"""Goodness of fit between real and synthetic pairs (docs/calibration.md):

- per-statistic distances: the 1-Wasserstein distance between the real and synthetic values of a
  statistic over pairs (exact, SciPy's), divided by the real values' interquartile range
  (scale-free; 0 = same distribution);
- a two-sample classifier test: an L2-regularised logistic regression on the standardised
  statistics, scored out of fold (leave one scene out, or 4 folds with one scene), its AUC (0.5 =
  indistinguishable) with a scene-bootstrap 95% interval;
- the real-vs-real floor: the same distances and AUC between two halves of the real pairs (by
  scene, else by pair), what "as close as real data is to itself" measures with this many pairs.

"matched" is said only within that floor: every statistic's distance at most its floor distance
plus 0.5 IQR, and the synthetic-vs-real AUC interval's lower end at or below the floor AUC
interval's upper end. The statistic furthest beyond its floor is always named. Pure functions of arrays (deterministic: fixed bootstrap seed).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["auc", "bootstrap_auc", "classifier_auc", "compare", "distances", "iqr_scale", "separation", "stat_matrix", "usable", "w1"]


def stat_matrix(stats: Sequence[dict[str, Any]], names: Sequence[str]) -> np.ndarray:
    """(pairs, statistics) of the named scalar statistics (None and NaN read as NaN)."""
    return np.array([[np.nan if s.get(n) is None else float(s[n]) for n in names] for s in stats], dtype=np.float64)


def usable(names: Sequence[str], *matrices: np.ndarray) -> list[int]:
    """Columns finite in every pair of every matrix."""
    return [k for k in range(len(names)) if all(np.all(np.isfinite(m[:, k])) for m in matrices)]


def w1(a: np.ndarray, b: np.ndarray) -> float:
    """The 1-Wasserstein distance between the empirical distributions of two samples, exact
    (`scipy.stats.wasserstein_distance`: the area between their step CDFs)."""
    try:
        from scipy.stats import wasserstein_distance
    except ImportError as e:  # pragma: no cover - metrics extra missing
        raise ImportError("calibration's distances need SciPy: pip install 'morphgs[metrics]'") from e
    return float(wasserstein_distance(a, b))


def iqr_scale(values: np.ndarray) -> float:
    """The interquartile range of `values`, floored at 1e-6 of their largest magnitude (and at
    1e-6), so that a distance divided by it is finite."""
    iqr = float(np.subtract(*np.quantile(values, [0.75, 0.25])))
    return max(iqr, 1e-6 * max(float(np.abs(values).max()), 1.0))


def distances(real: np.ndarray, synth: np.ndarray, names: Sequence[str]) -> dict[str, float]:
    """W1(real, synth) / IQR(real) per statistic (`w1`, `iqr_scale`)."""
    return {names[k]: w1(real[:, k], synth[:, k]) / iqr_scale(real[:, k]) for k in usable(names, real, synth)}


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney, ties count half); labels 1 = synthetic."""
    pos, neg = scores[labels == 1], scores[labels == 0]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    diff = pos[:, None] - neg[None, :]
    return float(np.mean((diff > 0) + 0.5 * (diff == 0)))


def separation(scores: np.ndarray, labels: np.ndarray) -> float:
    """How far apart the two labels' scores lie, in pooled standard deviations (d'): (mean of
    label 1 - mean of label 0) / sqrt((var 1 + var 0) / 2). Unlike the AUC it does not stop at
    perfect separation: two families both told apart every time (AUC 1.00) still differ in it.
    NaN with fewer than two scores of a label; +inf when both sides are constant and differ."""
    pos, neg = scores[labels == 1], scores[labels == 0]
    if len(pos) < 2 or len(neg) < 2:
        return float("nan")
    gap = float(np.mean(pos) - np.mean(neg))
    sd = float(np.sqrt(0.5 * (np.var(pos) + np.var(neg))))
    if sd == 0.0:
        return 0.0 if gap == 0.0 else math.copysign(math.inf, gap)
    return gap / sd


def _logistic(x: np.ndarray, y: np.ndarray, l2: float = 1.0, iters: int = 50) -> np.ndarray:
    """Weights (d + 1) of an L2-regularised logistic regression by Newton's method."""
    xb = np.hstack([x, np.ones((len(x), 1))])
    w = np.zeros(xb.shape[1])
    reg = l2 * np.eye(xb.shape[1])
    reg[-1, -1] = 1e-8
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-np.clip(xb @ w, -30, 30)))
        grad = xb.T @ (p - y) + reg @ w
        hess = (xb * (p * (1 - p))[:, None]).T @ xb + reg
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    return w


def classifier_auc(x: np.ndarray, y: np.ndarray, groups: Sequence[str], *, n_boot: int = 200,
                   seed: int = 0) -> dict[str, Any]:
    """Out-of-fold AUC of a logistic classifier telling y = 1 rows from y = 0 rows, and its
    scene-bootstrap 95% interval. Folds: leave one group (scene) out, or 4 interleaved folds
    when there is one group."""
    g = np.asarray(groups)
    uniq = sorted(set(g.tolist()))
    folds = [g == u for u in uniq]
    if len(uniq) < 2 or any(len(set(y[~f].tolist())) < 2 for f in folds):
        # one scene, or scenes that each hold one class (halves by scene): 4 folds interleaved per class
        rank = np.zeros(len(y), dtype=int)
        for c in (0, 1):
            rank[y == c] = np.arange(int(np.sum(y == c)))
        folds = [rank % 4 == k for k in range(4)]
    scores = np.zeros(len(y))
    for test in folds:
        train = ~test
        if not test.any() or len(set(y[train].tolist())) < 2:
            scores[test] = 0.0
            continue
        mu, sd = x[train].mean(0), x[train].std(0) + 1e-9
        w = _logistic((x[train] - mu) / sd, y[train])
        scores[test] = np.hstack([(x[test] - mu) / sd, np.ones((int(test.sum()), 1))]) @ w
    value = auc(scores, y)
    units = g if len(uniq) > 1 else np.arange(len(y))  # one scene: each row its own unit
    return {"auc": value, "ci": bootstrap_auc(scores, y, units, n_boot=n_boot, seed=seed),
            "bootstrap": "scenes" if len(uniq) > 1 else "pairs"}


def bootstrap_auc(scores: np.ndarray, labels: np.ndarray, units: np.ndarray, *, n_boot: int,
                  seed: int) -> list[float]:
    """The 95% interval of `auc` over `n_boot` resamples of the units (rows sharing a unit, e.g.
    a scene, are drawn together); NaN when no resample holds both labels."""
    uniq = sorted(set(units.tolist()))
    rng = np.random.default_rng(seed)
    boots = []
    for _ in range(n_boot):
        pick = rng.choice(len(uniq), size=len(uniq), replace=True)
        idx = np.concatenate([np.flatnonzero(units == uniq[i]) for i in pick])
        a = auc(scores[idx], labels[idx])
        if np.isfinite(a):
            boots.append(a)
    if not boots:
        return [float("nan"), float("nan")]
    lo, hi = np.quantile(boots, [0.025, 0.975])
    return [float(lo), float(hi)]


def _halves(groups: Sequence[str]) -> np.ndarray:
    """A boolean split of the real pairs into two halves: alternate scenes, else alternate pairs."""
    uniq = sorted(set(groups))
    if len(uniq) > 1:
        first = set(uniq[0::2])
        return np.array([g in first for g in groups])
    return np.arange(len(groups)) % 2 == 0


def compare(real_stats: Sequence[dict[str, Any]], synth_stats: Sequence[dict[str, Any]], real_groups: Sequence[str],
            synth_groups: Sequence[str], names: Sequence[str], *,
            floor_stats: Sequence[dict[str, Any]] | None = None, floor_groups: Sequence[str] | None = None,
            slack: float = 0.5) -> dict[str, Any]:
    """Distances, classifier AUC, the real-vs-real floor and the verdict (module doc).

    The floor is computed on `floor_stats` / `floor_groups` (all the real pairs; default: the
    compared real pairs). "matched": every statistic's distance within its floor distance plus
    `slack` (IQR units) and the AUC interval's lower end at or below the floor's upper end.
    """
    r, s = stat_matrix(real_stats, names), stat_matrix(synth_stats, names)
    fr = r if floor_stats is None else stat_matrix(floor_stats, names)
    fg = list(real_groups) if floor_groups is None else list(floor_groups)
    cols = usable(names, r, s)
    used = [names[k] for k in cols]
    dist = distances(r, s, names)
    x = np.vstack([r[:, cols], s[:, cols]])
    y = np.r_[np.zeros(len(r)), np.ones(len(s))]
    clf = classifier_auc(x, y, list(real_groups) + list(synth_groups))
    half = _halves(fg)
    floor: dict[str, Any] = {"distances": {}, "auc": float("nan"), "ci": [float("nan"), float("nan")],
                             "split": "scenes" if len(set(fg)) > 1 else "pairs"}
    if half.any() and (~half).any():
        a, b = fr[half], fr[~half]
        floor["distances"] = distances(a, b, names)
        xg = np.vstack([a[:, cols], b[:, cols]])
        yg = np.r_[np.zeros(len(a)), np.ones(len(b))]
        gg = [g for g, h in zip(fg, half) if h] + [g for g, h in zip(fg, half) if not h]
        f = classifier_auc(xg, yg, gg)
        floor["auc"], floor["ci"] = f["auc"], f["ci"]
    excess = {n: dist[n] - floor["distances"].get(n, 0.0) for n in dist}
    furthest = max(excess, key=lambda n: excess[n]) if excess else None
    within = all(e <= slack for e in excess.values()) and bool(floor["distances"])
    matched = bool(within and np.isfinite(floor["ci"][1]) and clf["ci"][0] <= floor["ci"][1])
    medians = {names[k]: [float(np.median(r[:, k])), float(np.median(s[:, k]))] for k in cols}
    return {"statistics": used, "distances": dist, "medians": medians, "classifier": clf, "floor": floor, "matched": matched,
            "furthest": furthest, "furthest_excess": excess.get(furthest) if furthest else None,
            "pairs": {"real": len(r), "synthetic": len(s)}}
