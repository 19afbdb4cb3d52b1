"""Writing an evaluation: per-frame CSV, Markdown tables, a JSON summary and per-clip plots.

Files are written to a temporary name and renamed, so a reader never sees half a table.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from pathlib import Path
from typing import Any

from morphgs.evaluation.types import METRICS, EvalReport

__all__ = ["markdown", "write_all", "write_csv", "write_plots"]


def _atomic_write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def _cell(metric: str, value: float) -> str:
    if isinstance(value, float) and math.isnan(value):
        return "–"
    if isinstance(value, float) and math.isinf(value):
        return "∞" if value > 0 else "-∞"
    return METRICS[metric].fmt.format(value)


def _header(metric: str, lpips_net: str) -> str:
    info = METRICS[metric]
    title = f"LPIPS ({lpips_net})" if metric == "lpips" else info.title
    return f"{title} {'↑' if info.higher_is_better else '↓'}"


def write_csv(report: EvalReport, path: Path) -> Path:
    """One row per frame: label, clip, frame, then each metric (empty where it has no value)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["label", "clip", "frame", *report.metrics])
    for row in report.rows:
        vals = ["" if math.isnan(row[m]) else repr(float(row[m])) for m in report.metrics]
        w.writerow([row["label"], row["clip"], row["frame"], *vals])
    return _atomic_write(path, buf.getvalue())


def markdown(report: EvalReport, *, lpips_net: str = "alex") -> str:
    """The per-clip table and the overall table (one row per label) as Markdown."""
    heads = [_header(m, lpips_net) for m in report.metrics]
    several = len(report.overall) > 1
    lines = ["# Evaluation", "", "## Overall", "",
             "mean over every frame of every clip (E_flow and E_warp: over consecutive frame pairs)", ""]
    lines += ["| " + " | ".join(["", "clips", "frames", *heads]) + " |", "|" + "---|" * (3 + len(heads))]
    for label, values in report.overall.items():
        clips = [c for c in report.clips if c["label"] == label]
        frames = sum(int(c["frames"]) for c in clips)
        cells = [_cell(m, values[m]) for m in report.metrics]
        lines.append("| " + " | ".join([label, str(len(clips)), str(frames), *cells]) + " |")
    lines += ["", "## Per clip", ""]
    first = ["clip", "label"] if several else ["clip"]
    lines += ["| " + " | ".join([*first, "frames", *heads]) + " |", "|" + "---|" * (len(first) + 1 + len(heads))]
    for c in report.clips:
        ident = [c["clip"], c["label"]] if several else [c["clip"]]
        cells = [_cell(m, c[m]) for m in report.metrics]
        lines.append("| " + " | ".join([*ident, str(c["frames"]), *cells]) + " |")
    return "\n".join(lines) + "\n"


def _json_value(v: Any) -> Any:
    if isinstance(v, float) and (math.isnan(v) or math.isinf(v)):
        return None if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return v


def _plot_name(clip: str, used: set[str]) -> str:
    """A file name for a clip's plot: path separators and odd characters become "__"."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "__", clip).strip("_.") or "clip"
    name, k = f"{stem}.png", 1
    while name in used:
        k += 1
        name = f"{stem}-{k}.png"
    used.add(name)
    return name


def write_plots(report: EvalReport, folder: Path) -> list[Path]:
    """One PNG per clip: each metric over the frames, one line per label. Needs matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("plots need matplotlib: pip install 'morphgs[metrics]' (or pass plots=False)") from e
    folder.mkdir(parents=True, exist_ok=True)
    clips = list(dict.fromkeys(c["clip"] for c in report.clips))
    labels = list(report.overall)
    written = []
    used: set[str] = set()
    for clip in clips:
        shown = [m for m in report.metrics
                 if any(r["clip"] == clip and not math.isnan(r[m]) and not math.isinf(r[m]) for r in report.rows)]
        if not shown:
            continue
        cols = 1 if len(shown) <= 5 else 2
        rows_n = -(-len(shown) // cols)
        fig = Figure(figsize=(7.0 * cols, 1.6 * rows_n + 0.6), layout="constrained")
        grid = fig.subplots(rows_n, cols, sharex=True, squeeze=False)
        axes = grid.T.reshape(-1)[: len(shown)]       # fill column by column
        for spare in grid.T.reshape(-1)[len(shown):]:
            spare.set_visible(False)
        for ax, m in zip(axes, shown):
            for label in labels:
                rows = [r for r in report.rows if r["clip"] == clip and r["label"] == label]
                xs = [r["frame"] for r in rows if math.isfinite(r[m])]
                ys = [r[m] for r in rows if math.isfinite(r[m])]
                if xs:
                    ax.plot(xs, ys, marker=".", markersize=3, linewidth=1, label=label)
            info = METRICS[m]
            ax.set_ylabel(f"{info.title} {'↑' if info.higher_is_better else '↓'}", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
        fig.suptitle(clip, fontsize=9)
        for ax in grid[-1]:
            ax.set_xlabel("frame", fontsize=8)
        if len(labels) > 1:
            axes[0].legend(fontsize=7)
        path = folder / _plot_name(clip, used)
        tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.png")
        fig.savefig(tmp, dpi=100)
        os.replace(tmp, path)
        written.append(path)
    return written


def write_all(report: EvalReport, out_dir: Path, *, plots: bool = True, lpips_net: str = "alex") -> dict[str, Any]:
    """per_frame.csv, summary.md, summary.json and plots/*.png under `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, Any] = {
        "csv": write_csv(report, out_dir / "per_frame.csv"),
        "markdown": _atomic_write(out_dir / "summary.md", markdown(report, lpips_net=lpips_net)),
    }
    summary = {
        "metrics": report.metrics,
        "lpips_net": lpips_net,
        "overall": {k: {m: _json_value(v) for m, v in d.items()} for k, d in report.overall.items()},
        "clips": [{k: _json_value(v) for k, v in c.items()} for c in report.clips],
    }
    files["json"] = _atomic_write(out_dir / "summary.json", json.dumps(summary, indent=1) + "\n")
    files["plots"] = write_plots(report, out_dir / "plots") if plots else []
    return files
