"""The report's plots (matplotlib, Agg): each condition's paired difference from the unrefined
input with its 95 % CI per regime (deltas.png), CKA against
training step (the paper's Fig. 5), and a qualitative sheet (conditions as rows, the frames of one
test clip as columns; the paper's Fig. 4)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.ablation.conditions import Condition
from morphgs.ablation.stats import mean_ci
from morphgs.ablation.table import COLUMNS, units

__all__ = ["DELTA_METRICS", "deltas", "paired_differences", "write_all"]


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: The metrics whose paired differences `deltas` draws (key in the records, title).
DELTA_METRICS = (("psnr2d", "PSNR2D"), ("ssim2d", "SSIM2D"), ("psnr3d", "PSNR3D"))


def paired_differences(records: Sequence[dict[str, Any]], regime: str, conditions: Sequence[str], key: str,
                       reference: str) -> dict[str, tuple[float, float, int]]:
    """{condition: (mean, 95 % CI half-width, n)} of `key`'s paired difference condition -
    reference over (test scene, seed) units of `regime` (the clips of a unit averaged first). A
    control reference (input, ...) has one unit per scene, paired with every seed of the scene."""
    ref = units([r for r in records if r["regime"] == regime and r["condition"] == reference], key)
    by_scene = {scene: v for (scene, seed), v in ref.items() if seed is None}
    out = {}
    for c in conditions:
        if c == reference:
            continue
        mine = units([r for r in records if r["regime"] == regime and r["condition"] == c], key)
        d = [v - (ref[k] if k in ref else by_scene[k[0]]) for k, v in mine.items() if k in ref or k[0] in by_scene]
        out[c] = mean_ci(d)
    return out


def deltas(out: Path, records: Sequence[dict[str, Any]], regimes: Sequence[str], conditions: Sequence[str]) -> None:
    """deltas.png: per regime (a row of panels), each condition's paired difference from the
    unrefined input in PSNR2D, SSIM2D and PSNR3D (and the identity row; not the oracle), with its
    95 % CI and a zero line; the regime's target as a dashed line. Higher is better in all three."""
    plt = _plt()
    cols = len(DELTA_METRICS)
    fig, axes = plt.subplots(len(regimes), cols, figsize=(3.3 * cols, 0.35 * len(conditions) + 1.4 * len(regimes)),
                             squeeze=False)
    for i, rg in enumerate(regimes):
        # not the oracle: the ceiling, whose gap would squeeze every other row to the zero line
        rows = [c for c in conditions if Condition.parse(c).in_regime(rg)] + ["identity"]
        target = f"target-{rg}"
        for j, (key, name) in enumerate(DELTA_METRICS):
            ax = axes[i][j]
            diff = paired_differences(records, rg, rows, key, "input")
            ys = np.arange(len(rows))[::-1]
            for y, c in zip(ys, rows):
                m, ci, _ = diff.get(c, (math.nan, math.nan, 0))
                if not math.isfinite(m):
                    continue
                kind = Condition.parse(c).kind
                colour = {"control": "0.55", "target": "C3", "calibrated": "C2"}.get(kind, "C0")
                ax.errorbar(m, y, xerr=ci if math.isfinite(ci) else None, fmt="o", color=colour, ms=3.5, capsize=2,
                            lw=1)
            if target in diff and math.isfinite(diff[target][0]):
                ax.axvline(diff[target][0], color="C3", ls="--", lw=0.8)
            ax.axvline(0.0, color="k", lw=0.8)
            ax.set_yticks(ys)
            ax.set_yticklabels([Condition.parse(c).label if j == 0 else "" for c in rows], fontsize=7)
            ax.set_title(f"{rg}: {name} − input", fontsize=8)
            ax.tick_params(axis="x", labelsize=7)
            ax.grid(axis="x", lw=0.3, alpha=0.5)
    fig.tight_layout()
    fig.savefig(out / "deltas.png", dpi=100, metadata={"Software": None})
    plt.close(fig)


def cka(out: Path, curves: Sequence[dict[str, Any]]) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    names = sorted({c["condition"] for c in curves})
    for k, name in enumerate(names):
        for n, c in enumerate(x for x in curves if x["condition"] == name):
            ax.plot(c["steps"], c["mean"], color=f"C{k % 10}", lw=1, label=Condition.parse(name).label if n == 0 else None, alpha=0.8)
    ax.set_xlabel("training step")
    ax.set_ylabel("linear CKA vs initial (temporal features)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "cka.png", dpi=90, metadata={"Software": None})
    plt.close(fig)


def sheet(out: Path, parts: Sequence[tuple[str, str, dict[str, Any]]], conditions: Sequence[str]) -> None:
    """Rows: oracle, input, then each condition's first seed; columns: the clip's frames."""
    from morphgs import media

    refs = [(Path(p), m) for s, p, m in parts if s == "refine"]
    if not refs:
        return
    first = refs[0][1]
    pick = {m["condition"]: p for p, m in reversed(refs)
            if m["scene"] == first["scene"] and m["regime"] == first["regime"]}
    rows = [r for r in ["oracle", "input", *conditions] if r in pick]
    strips = []
    for r in rows:
        frames = media.read_clip(pick[r] / "clips" / "00" / "frames")
        step = max(1, len(frames) // 8)
        strips.append(np.concatenate(list(frames[::step][:8]), axis=1))
    plt = _plt()
    h, w = strips[0].shape[:2]
    fig, axes = plt.subplots(len(rows), 1, figsize=(min(16, w / 40 + 1), (h / 40 + 0.3) * len(rows)), squeeze=False)
    for ax, r, s in zip(axes[:, 0], rows, strips):
        ax.imshow(s)
        ax.set_ylabel(Condition.parse(r).label, rotation=0, ha="right", fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{first['scene']} {first['regime']}, clip 00", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "qualitative.png", dpi=90, metadata={"Software": None})
    plt.close(fig)


def write_all(out: Path, g: dict[str, Any], *, regimes: Sequence[str], conditions: Sequence[str],
              parts: Sequence[tuple[str, str, dict[str, Any]]]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    deltas(out, g["records"], regimes, conditions)
    cka(out, g["cka"])
    sheet(out, parts, conditions)
