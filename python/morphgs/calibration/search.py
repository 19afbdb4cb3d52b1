"""The strength search of one family against one set of real pairs (docs/calibration.md).

`measure(s)` returns the per-frame PSNR of the synthetic pairs at strength s: the same cameras as
the real pairs (frame j of the synthetic set is rendered from the camera of real frame j) and
the same seeds at every s (common random numbers), so each frame has its own severity curve
T_j(s). The search:

1. scans a log grid of s and checks that severity rises with s (median PSNR falls); where it
   does not, the result says so (`monotone` False, the offending grid steps in `violations`);
2. bisects (in log s) to the strength whose median synthetic PSNR is the real median PSNR;
3. matches quantiles: frame j's strength s_j solves T_j(s_j) = real PSNR of frame j (on the
   decreasing envelope of T_j over the evaluated points, interpolated in log s); the strength
   distribution is the quantile table of the s_j. Real severity varies with each frame's distance
   to the training views, and so does s_j. Given each frame's pair, the table is over pairs
   instead (pair k's strength matches its median PSNR), since curate draws one strength per pair;
   `unreachable_frames` and `below_grid_frames` then count pairs;
4. frames more severe than the most severe value the family reaches are **unreachable**: their
   s_j is the most severe grid strength and they are counted (never clipped silently); when the
   real median itself is out of reach, the family is unreachable for these pairs, with the most
   severe median PSNR it does reach. Frames milder than the smallest grid strength get it and are
   counted too (`below_grid_frames`).

These functions are pure: they take `measure` and return plain data.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

__all__ = ["DEFAULT_GRID", "PROBS", "SearchResult", "frame_strengths", "log_grid", "monotone_envelope",
           "monotonicity", "search"]

Measure = Callable[[float], np.ndarray]

#: Probabilities of the strength quantile table.
PROBS: tuple[float, ...] = (0.0, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95, 1.0)


def log_grid(lo: float = 2.0**-4, hi: float = 2.0**7, per_octave: int = 2) -> list[float]:
    """Strengths lo * 2^(k / per_octave) up to hi (a log grid)."""
    n = int(round(math.log2(hi / lo) * per_octave))
    return [float(lo * 2.0 ** (k / per_octave)) for k in range(n + 1)]


DEFAULT_GRID: tuple[float, ...] = tuple(log_grid())


def monotonicity(strengths: Sequence[float], medians: Sequence[float], tol_db: float = 0.1) -> list[dict[str, float]]:
    """Grid steps where severity falls: the median PSNR rises by more than `tol_db` from one
    strength to the next. Empty when severity rises monotonically with strength."""
    out = []
    for (s0, p0), (s1, p1) in zip(zip(strengths, medians), zip(strengths[1:], medians[1:])):
        if p1 > p0 + tol_db:
            out.append({"from_strength": s0, "to_strength": s1, "from_psnr": p0, "to_psnr": p1})
    return out


def monotone_envelope(psnr: np.ndarray) -> np.ndarray:
    """The non-increasing envelope along the last axis (running minimum): the severity reached by
    strengths up to each point (so a non-monotone curve is inverted at its first crossing)."""
    return np.minimum.accumulate(psnr, axis=-1)  # type: ignore[no-any-return]


def frame_strengths(strengths: np.ndarray, curves: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's strength s_j with T_j(s_j) = target_j.

    Args:
        strengths: (S,) increasing, > 0. curves: (F, S) synthetic PSNR of frame j at each
            strength. targets: (F,) real PSNR of frame j.

    Returns:
        (s (F,), unreachable (F,) bool): T_j's envelope is interpolated linearly in log s; a target
        above the envelope at the smallest strength gets the smallest strength; a target below its
        minimum is unreachable and gets the strength where the minimum is reached.
    """
    env = monotone_envelope(curves)
    logs = np.log(strengths)
    out = np.empty(len(targets))
    unreachable = np.zeros(len(targets), dtype=bool)
    for j, (t, e) in enumerate(zip(targets, env)):
        if t >= e[0]:
            out[j] = strengths[0]
        elif t < e[-1]:
            unreachable[j] = True
            out[j] = strengths[int(np.argmax(e <= e[-1]))]
        else:
            k = int(np.argmax(e <= t))  # first point at or below the target; e[k-1] > t
            p0, p1 = e[k - 1], e[k]
            w = (p0 - t) / (p0 - p1) if p0 > p1 else 1.0
            out[j] = math.exp(logs[k - 1] + w * (logs[k] - logs[k - 1]))
    return out, unreachable


@dataclass
class SearchResult:
    """What the search found (every field is JSON-ready via `to_dict`)."""

    target_median_psnr: float
    grid: list[float]
    grid_median_psnr: list[float]
    monotone: bool
    violations: list[dict[str, float]]
    reachable: bool
    most_severe_psnr: float
    most_severe_strength: float
    median_strength: float | None
    median_psnr_reached: float | None
    bisection: list[tuple[float, float]]
    quantiles: dict[str, list[float]]
    unreachable_frames: float
    below_grid_frames: float = 0.0
    frame_strengths: list[float] = field(default_factory=list)
    pair_strengths: list[float] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _bisect(measure: Measure, target: float, lo: float, hi: float, *, tol_db: float, iters: int,
            log: list[tuple[float, float]]) -> tuple[float, float]:
    """Strength in [lo, hi] (median PSNR above / below target at the ends) whose median PSNR is
    within tol_db of target, by bisection in log s."""
    best = (lo, math.inf)
    for _ in range(iters):
        mid = math.sqrt(lo * hi)
        m = float(np.median(measure(mid)))
        log.append((mid, m))
        if abs(m - target) < abs(best[1] - target):
            best = (mid, m)
        if abs(m - target) <= tol_db:
            return mid, m
        if m > target:
            lo = mid
        else:
            hi = mid
    return best


def search(measure: Measure, real_frame_psnr: Sequence[float] | np.ndarray, *, grid: Sequence[float] = DEFAULT_GRID,
           probs: Sequence[float] = PROBS, tol_db: float = 0.05, iters: int = 10,
           pairs: Sequence[int] | np.ndarray | None = None) -> SearchResult:
    """Scan, check monotonicity, bisect to the real median PSNR, match quantiles (module doc).

    Args:
        measure: strength -> per-frame synthetic PSNR (F,), frames aligned with `real_frame_psnr`.
        real_frame_psnr: the real pairs' per-frame PSNR (F,).
        grid: increasing strengths > 0 (a log grid). probs: the quantile table's probabilities.
        tol_db: bisection tolerance and the monotonicity check's tolerance. iters: bisection steps.
        pairs: the pair index of each frame. When given, the quantile table is over pairs: pair
            k's strength solves median_j∈k T_j(s) = the real pair's median PSNR (curate draws one
            strength per pair); the per-frame strengths are still reported.
    """
    cache: dict[float, np.ndarray] = {}
    raw = measure

    def memo(s: float) -> np.ndarray:  # every strength is rendered once
        if s not in cache:
            cache[s] = np.asarray(raw(s), dtype=np.float64)
        return cache[s]

    measure = memo
    real = np.asarray(real_frame_psnr, dtype=np.float64)
    g = np.asarray(sorted(float(s) for s in grid))
    if len(g) < 2 or g[0] <= 0:
        raise ValueError("the strength grid needs at least two strengths > 0")
    curves = np.stack([np.asarray(measure(float(s)), dtype=np.float64) for s in g], axis=1)  # (F, S)
    if curves.shape[0] != len(real):
        raise ValueError(f"measure gave {curves.shape[0]} frames for {len(real)} real frames")
    medians = np.median(curves, axis=0)
    violations = monotonicity(g.tolist(), medians.tolist(), tol_db=max(tol_db, 0.1))
    target = float(np.median(real))
    k_min = int(np.argmin(medians))
    most_severe = float(medians[k_min])
    reachable = target >= most_severe
    bis: list[tuple[float, float]] = []
    med_s: float | None = None
    med_p: float | None = None
    if reachable:
        env = monotone_envelope(medians)
        if target >= env[0]:
            med_s, med_p = float(g[0]), float(medians[0])
        else:
            k = int(np.argmax(env <= target))
            med_s, med_p = _bisect(measure, target, float(g[k - 1]), float(g[k]), tol_db=tol_db, iters=iters, log=bis)
    # per-frame strengths over every evaluated point (grid + bisection), in strength order
    pts = sorted(cache)
    all_s = np.asarray(pts)
    all_curves = np.stack([cache[s] for s in pts], axis=1)
    s_j, unreach = frame_strengths(all_s, all_curves, real)
    below = real >= monotone_envelope(all_curves)[:, 0]
    pair_s: list[float] = []
    matched = s_j
    if pairs is not None:
        ids = np.asarray(pairs)
        if ids.shape != real.shape:
            raise ValueError(f"pairs gives {ids.shape[0]} frames for {len(real)} real frames")
        keys = sorted(set(ids.tolist()))
        curves_p = np.stack([np.median(all_curves[ids == k], axis=0) for k in keys])
        targets_p = np.array([np.median(real[ids == k]) for k in keys])
        sp, unreach_p = frame_strengths(all_s, curves_p, targets_p)
        pair_s, matched = sp.tolist(), sp
        unreach = unreach_p
        below = targets_p >= monotone_envelope(curves_p)[:, 0]
    q = np.quantile(matched, probs)
    q = np.maximum.accumulate(q)
    return SearchResult(
        target_median_psnr=target, grid=g.tolist(), grid_median_psnr=medians.tolist(),
        monotone=not violations, violations=violations, reachable=reachable,
        most_severe_psnr=most_severe, most_severe_strength=float(g[k_min]),
        median_strength=med_s, median_psnr_reached=med_p, bisection=bis,
        quantiles={"p": [float(p) for p in probs], "strength": [float(v) for v in q]},
        unreachable_frames=float(unreach.mean()), below_grid_frames=float(below.mean()),
        frame_strengths=s_j.tolist(), pair_strengths=pair_s)
