"""The op-mix search (opt-in, `morphgs calibrate --search-mix`): which mix of a family's ops makes
pairs that resemble the real ones in more than PSNR (docs/calibration.md, "Op mix").

A mix is a weight vector w over the family's n ops, on a simplex grid (every w_k a multiple of
1/steps, sum 1; the preset's proportions w_k = 1/n are always a candidate). Op k of a mix runs at
n * w_k times the family's strength: its base value b_k becomes b_k ** (n w_k) for keep (the
keep fraction's exponent) and n w_k * b_k for the others, so the preset mix is the family itself
and an op with w_k = 0 is off. Each mix is matched to the real pairs' PSNR (the strength search,
pair by pair), and its pairs at their matched strengths are compared with the real ones on the
other statistics: SSIM, LPIPS (when computed), colour shift, coverage, temporal error and the
error spectrum (its bands averaged into one term, so that they count as one statistic). The
distance of a statistic is W1(real, synthetic) over pairs divided by the interquartile range of
the real and every candidate's values pooled (`goodness.w1`, `goodness.iqr_scale`) (a scale shared by the candidates, never the IQR of
a handful of real values alone); a mix's score is the mean distance over the statistics. The mix
with the lowest score wins (ties: the earlier candidate, the preset first).

These are pure functions of plain data.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from morphgs.calibration import stats
from morphgs.calibration.goodness import iqr_scale, w1
from morphgs.strength import Strength

__all__ = ["GROUPS", "mix_distances", "mixed", "simplex_grid"]

#: The statistics a mix is judged on (PSNR is matched by construction), spectrum bands as one.
GROUPS: dict[str, tuple[str, ...]] = {
    "ssim": ("ssim",),
    "lpips": ("lpips",),
    "color_shift": ("color_shift",),
    "coverage": ("coverage",),
    "temporal_error": ("temporal_error",),
    "spectrum": stats.SPECTRUM_NAMES,
}


def simplex_grid(ops: Sequence[str], steps: int = 3) -> list[dict[str, float]]:
    """The preset mix (1/n each) first, then every w with w_k in {0, 1/steps, ..., 1}, sum 1.

    Raises:
        ValueError: steps < 1 or no ops.
    """
    if steps < 1 or not ops:
        raise ValueError(f"a mix grid needs ops and steps >= 1, got {len(ops)} op(s) and steps={steps}")
    n = len(ops)
    out = [dict.fromkeys(ops, 1.0 / n)]
    for c in itertools.product(range(steps + 1), repeat=n):
        if sum(c) == steps:
            w = {op: k / steps for op, k in zip(ops, c)}
            if any(abs(w[op] - 1.0 / n) > 1e-12 for op in ops):
                out.append(w)
    # the most spread mixes (many ops on) before the single-op corners, then lexicographic
    head, rest = out[:1], out[1:]
    rest.sort(key=lambda w: (-sum(v > 0 for v in w.values()), [-w[op] for op in ops]))
    return head + rest


def mixed(base: Strength, weights: Mapping[str, float]) -> Strength:
    """`base` with its ops re-weighted by the mix `weights` (ops of weight 0 disabled)."""
    n = len(weights)
    ops = {}
    for op, w in weights.items():
        if w <= 0.0:
            continue
        b, m = base.base[op], n * float(w)
        ops[op] = b ** m if op == "keep" else m * b
    return Strength(base.family, 1.0, ops)


def _column(stats: Sequence[Mapping[str, Any]], name: str) -> np.ndarray:
    return np.array([np.nan if s.get(name) is None else float(s[name]) for s in stats], dtype=np.float64)


def mix_distances(real: Sequence[Mapping[str, Any]],
                  candidates: Sequence[Sequence[Mapping[str, Any]]]) -> list[dict[str, Any]]:
    """Each candidate's distance to the real pairs per statistic group and its score (module doc).

    Args:
        real: the real pairs' `stats.pair_stats`. candidates: per mix, its synthetic pairs' stats.

    Returns:
        Per candidate {"distances": {group: distance}, "score": mean over the groups}; a group
        (or a band) with a non-finite value anywhere is left out for every candidate.
    """
    per: list[dict[str, float]] = [{} for _ in candidates]
    for group, names in GROUPS.items():
        parts: list[list[float]] = [[] for _ in candidates]
        for name in names:
            r = _column(real, name)
            cs = [_column(c, name) for c in candidates]
            if len(r) == 0 or not all(np.all(np.isfinite(v)) and len(v) for v in [r, *cs]):
                continue
            scale = iqr_scale(np.concatenate([r, *cs]))
            for k, c in enumerate(cs):
                parts[k].append(w1(r, c) / scale)
        for k, p in enumerate(parts):
            if p:
                per[k][group] = float(np.mean(p))
    return [{"distances": d, "score": float(np.mean(list(d.values()))) if d else float("nan")} for d in per]
