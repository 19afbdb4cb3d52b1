"""The table of a study (the paper's Table 1 layout), from per-clip records: pure functions, no
files. Rows are the conditions grouped by regime (the training sets, then the regime's target),
then the control rows (input, identity, oracle; they do not compete for best); columns are
Table 1's nine metrics; each regime's heading says where its inputs sit beside the paper's. Cells are the mean +- 95 % CI over (test scene, seed) units (the clips of
a unit averaged first); best in bold, second best in italics. Each row prints its severity (the
PSNR of its own training pairs); below, paired tests against `naive`, against the regime's
target, and of each calibrated condition against its family at the default strength.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from morphgs.ablation.conditions import CONTROLS, Condition
from morphgs.ablation.stats import mean_ci, paired_permutation_p

__all__ = ["COLUMNS", "format_table", "rank_marks", "units"]

# (key in the records, header, higher is better, digits)
COLUMNS = (("psnr2d", "PSNR2D", True, 3), ("ssim2d", "SSIM2D", True, 3), ("lpips2d", "LPIPS2D", False, 3),
           ("eflow", "Eflow", False, 3), ("psnr3d", "PSNR3D", True, 3), ("ssim3d", "SSIM3D", True, 3),
           ("lpips3d", "LPIPS3D", False, 3), ("chamfer", "CD", False, 4), ("f@1%", "F@1%", True, 3))


def rank_marks(means: dict[str, float], higher_better: bool) -> dict[str, str]:
    """{row: "best" | "second"} of the rows with the best and second-best finite mean (ties share
    a mark); rows without a finite mean get no mark."""
    vals = sorted({v for v in means.values() if v is not None and math.isfinite(v)}, reverse=higher_better)
    out = {}
    for row, v in means.items():
        if v is None or not math.isfinite(v):
            continue
        if v == vals[0]:
            out[row] = "best"
        elif len(vals) > 1 and v == vals[1]:
            out[row] = "second"
    return out


def units(records: Sequence[dict[str, Any]], key: str) -> dict[tuple[str, Any], float]:
    """{(scene, seed): mean over that unit's clips} of one metric (None values skipped)."""
    acc: dict[tuple[str, Any], list[float]] = {}
    for r in records:
        v = r.get(key)
        if v is not None:
            acc.setdefault((r["scene"], r["seed"]), []).append(float(v))
    return {k: sum(v) / len(v) for k, v in sorted(acc.items(), key=lambda kv: (kv[0][0], str(kv[0][1])))}


def _fmt(m: float, ci: float, digits: int) -> str:
    if math.isnan(m):
        return "n/a"
    if math.isinf(m):
        return "inf"
    return f"{m:.{digits}f} ± {ci:.{digits}f}" if not math.isnan(ci) else f"{m:.{digits}f}"


def format_table(records: Sequence[dict[str, Any]], *, regimes: Sequence[str], conditions: Sequence[str],
                 severity: dict[str, float], notes: Sequence[str] = ()) -> str:
    """table.md from per-clip records ({regime, condition, seed, scene, clip, metric: value})."""
    lines = ["# Ablation (the paper's Table 1 layout)", "",
             "Cells: mean ± 95 % CI over test scenes × seeds (clips of a scene averaged first). "
             "**Best**, *second best* among the trained conditions of a regime. Severity: PSNR (dB) of the "
             "condition's own training pairs, corrupted vs clean. Control rows do not compete.", ""]
    head = "| regime | training set | severity | " + " | ".join(c[1] for c in COLUMNS) + " |"
    sep = "|" + "---|" * (3 + len(COLUMNS))
    tests: list[str] = []
    for rg in regimes:
        rows = [c for c in conditions if Condition.parse(c).in_regime(rg)]
        target = f"target-{rg}" if f"target-{rg}" in conditions else None
        by_row = {c: [r for r in records if r["regime"] == rg and r["condition"] == c] for c in [*rows, *CONTROLS]}
        cells: dict[str, dict[str, str]] = {c: {} for c in by_row}
        for key, _, higher, digits in COLUMNS:
            stats = {c: mean_ci(list(units(by_row[c], key).values())) for c in by_row}
            marks = rank_marks({c: stats[c][0] for c in rows}, higher)
            for c, (m, ci, _) in stats.items():
                s = _fmt(m, ci, digits)
                mk = marks.get(c)
                cells[c][key] = f"**{s}**" if mk == "best" else f"*{s}*" if mk == "second" else s
        inp = mean_ci(list(units(by_row["input"], "psnr2d").values()))[0] if "input" in by_row else float("nan")
        where = (f"inputs (the sparse-view renders) at PSNR2D {inp:.2f} dB; the paper's sit at 12.9-17.1 dB"
                 if math.isfinite(inp) else "no input PSNR")
        lines += [f"## {rg}", "", f"{rg}: {where}.", "", head, sep]
        for c in [*rows, *CONTROLS]:
            sev = severity.get(c)
            sev_s = f"{sev:.2f}" if sev is not None else "-"
            name = Condition.parse(c).label if c not in CONTROLS else f"({c})"
            lines.append(f"| {rg} | {name} | {sev_s} | " + " | ".join(cells[c][k] for k, *_ in COLUMNS) + " |")
        lines.append("")
        for ref in (["naive"] if "naive" in conditions else []) + ([target] if target else []):
            tests += _paired_tests(f"{rg}: each condition − {Condition.parse(ref).label}",
                                   [(c, ref) for c in rows if c != ref], by_row)
        # a calibrated condition against its family at the default strength (the calibration's own effect)
        pairs = [(c, fam) for c in rows if (fam := Condition.parse(c).family) is not None and fam in conditions]
        if pairs:
            tests += _paired_tests(f"{rg}: each calibrated condition − its family at the default strength", pairs,
                                   by_row)
    if tests:
        lines += ["## Paired tests", "", *tests]
    if notes:
        lines += ["## Notes", "", *[f"- {n}" for n in notes], ""]
    return "\n".join(lines).rstrip("\n") + "\n"


def _paired_tests(title: str, pairs: Sequence[tuple[str, str]], by_row: dict[str, list[dict[str, Any]]]) -> list[str]:
    """A paired-test table: per (condition, reference), the mean paired difference over (scene,
    seed) units and its sign-flip permutation p, per metric."""
    out = [f"### {title} (mean paired difference, sign-flip permutation p)", "",
           "| condition | " + " | ".join(c[1] for c in COLUMNS) + " |", "|" + "---|" * (1 + len(COLUMNS))]
    for c, ref in pairs:
        cells = []
        for key, _, _, digits in COLUMNS:
            a, b = units(by_row[c], key), units(by_row[ref], key)
            common = [k for k in a if k in b]
            if len(common) < 2:
                cells.append("n/a")
                continue
            d = sum(a[k] - b[k] for k in common) / len(common)
            p = paired_permutation_p([a[k] for k in common], [b[k] for k in common])
            cells.append(f"{d:+.{digits}f} (p={p:.3f})" if math.isfinite(d) and not math.isnan(p) else "n/a")
        out.append(f"| {Condition.parse(c).label} | " + " | ".join(cells) + " |")
    return [*out, ""]


