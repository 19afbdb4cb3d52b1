"""The report's plots (matplotlib, Agg): per-metric bars with 95 % CIs per regime, CKA against
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

__all__ = ["write_all"]


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def bars(out: Path, records: Sequence[dict[str, Any]], regimes: Sequence[str], conditions: Sequence[str]) -> None:
    plt = _plt()
    fig, axes = plt.subplots(len(regimes), len(COLUMNS), figsize=(2.6 * len(COLUMNS), 2.6 * len(regimes)),
                             squeeze=False)
    for i, rg in enumerate(regimes):
        rows = [c for c in conditions if Condition.parse(c).in_regime(rg)] + ["input"]
        for j, (key, name, _, _) in enumerate(COLUMNS):
            ax = axes[i][j]
            ms, cis = [], []
            for c in rows:
                m, ci, _ = mean_ci(list(units([r for r in records if r["regime"] == rg and r["condition"] == c],
                                               key).values()))
                ms.append(m if math.isfinite(m) else 0.0)
                cis.append(ci if math.isfinite(ci) else 0.0)
            kinds = [Condition.parse(c).kind for c in rows]
            colors = [{"control": "0.6", "target": "C3", "calibrated": "C2"}.get(k, "C0") for k in kinds]
            ax.bar(range(len(rows)), ms, yerr=cis, color=colors, capsize=2)
            ax.set_xticks(range(len(rows)))
            ax.set_xticklabels([Condition.parse(c).label for c in rows], rotation=70, fontsize=6)
            ax.set_title(f"{rg} {name}", fontsize=8)
            ax.tick_params(axis="y", labelsize=6)
    fig.tight_layout()
    fig.savefig(out / "bars.png", dpi=90, metadata={"Software": None})
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
    bars(out, g["records"], regimes, conditions)
    cka(out, g["cka"])
    sheet(out, parts, conditions)
