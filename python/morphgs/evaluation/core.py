"""`evaluate`: every metric of every clip pair, per frame, then per clip and overall.

Conventions:
- Frame metrics (PSNR, SSIM, LPIPS, depth errors) have one value per frame; the pair metrics
  (E_flow, E_warp) one per consecutive pair (t-1, t), stored on frame t (frame 0 has none).
- A clip's value is the mean over its frames (or pairs); the overall value of a label is the
  mean over all frames (or pairs) of all its clips, so long clips weigh more. NaN (an empty mask,
  a depth map with no valid pixel) is skipped.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs import media
from morphgs._core import MorphgsError
from morphgs.evaluation.types import DEFAULT_METRICS, METRICS, SELECTABLE, Clip, ClipPair, EvalError, EvalReport

__all__ = ["DEFAULT_METRICS", "METRICS", "ClipPair", "EvalError", "EvalReport", "evaluate"]


def _check_metrics(metrics: Sequence[str]) -> list[str]:
    chosen = list(dict.fromkeys(metrics))
    bad = [m for m in chosen if m not in SELECTABLE]
    if bad:
        raise EvalError(f"unknown metric {bad[0]!r}; choose from {', '.join(SELECTABLE)}")
    if not chosen:
        raise EvalError("no metric chosen")
    return chosen


def _load_clip(clip: Clip, what: str, name: str) -> np.ndarray:
    if isinstance(clip, np.ndarray):
        a = clip
    else:
        a = media.read_clip(clip)
    if a.ndim != 4 or a.shape[-1] != 3 or len(a) == 0:
        raise EvalError(f"{name}: {what} must be a clip (F, H, W, 3), got shape {a.shape}")
    return a


def _load_depth(depth: Clip, what: str, name: str) -> np.ndarray:
    """Depth maps from an array or a folder: its `*.depth.exr` files (as `Render.save` and
    `morphgs curate --depth` name them, beside `*.alpha.exr`), else all its `*.exr` files."""
    if isinstance(depth, np.ndarray):
        d = depth
    else:
        folder = Path(depth)
        named = sorted(folder.glob("*.depth.exr")) if folder.is_dir() else []
        d = media.read_depth(named if named else folder)
    if d.ndim != 3:
        raise EvalError(f"{name}: {what} must be depth maps (F, H, W), got shape {d.shape}")
    return d


def _describe(a: np.ndarray) -> str:
    return f"{a.shape[0]} frames of {a.shape[2]}x{a.shape[1]}"


def _same_size(pair: ClipPair, pred: np.ndarray, gt: np.ndarray, what: tuple[str, str]) -> None:
    if pred.shape[:3] != gt.shape[:3]:
        raise EvalError(f"{pair.name}: {what[0]} has {_describe(pred)} but {what[1]} has {_describe(gt)} "
                        f"({_source(pair, what[0])} vs {_source(pair, what[1])})")


def _source(pair: ClipPair, what: str) -> str:
    v = {"pred": pair.pred, "gt": pair.gt, "depth_pred": pair.depth_pred, "depth_gt": pair.depth_gt}[what]
    return "an array" if isinstance(v, np.ndarray) else str(v)


def _same_clip(a: Clip, b: Clip) -> bool:
    """Whether two clip sources are the same clip: one array object, or one resolved path."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return a is b
    return Path(a).resolve() == Path(b).resolve()


def _partner_pred(partner: ClipPair | None, gt: np.ndarray) -> np.ndarray | None:
    """The next pair's prediction, when it scores against this pair's target and loads with the
    target's shape; else None (its own turn then reports any problem, in its own name)."""
    if partner is None:
        return None
    try:
        other = _load_clip(partner.pred, "pred", partner.name)
    except (MorphgsError, OSError):
        return None
    return other if other.shape == gt.shape else None


#: A pair's prediction, loaded, and its per-frame LPIPS, computed with the previous pair's.
_Handoff = tuple[np.ndarray, np.ndarray]


def _clip_metrics(pair: ClipPair, chosen: list[str], opts: dict[str, Any], step: Callable[[str], None], *,
                  handed: _Handoff | None = None,
                  partner: ClipPair | None = None) -> tuple[dict[str, np.ndarray], _Handoff | None]:
    """{metric: (F,) values} for one pair (pair metrics NaN on frame 0). `handed`: this pair's
    prediction and LPIPS from the previous pair's turn. `partner`: the next pair when it shares
    this pair's target; its LPIPS is then computed here, with the target's LPIPS features
    computed once for both, and handed over (the second value)."""
    from morphgs import metrics as M

    pred = handed[0] if handed is not None else _load_clip(pair.pred, "pred", pair.name)
    gt = _load_clip(pair.gt, "gt", pair.name)
    _same_size(pair, pred, gt, ("pred", "gt"))
    n = len(gt)
    out: dict[str, np.ndarray] = {}
    handoff: _Handoff | None = None
    for name, fn in (("psnr", M.psnr), ("ssim", M.ssim), ("color_shift", M.color_shift)):
        if name in chosen:
            step(name)
            out[name] = np.asarray(fn(pred, gt, reduction="none"), dtype=np.float64)
    if "lpips" in chosen:
        step("lpips")
        lp = {"net": opts["lpips_net"], "weights": opts["lpips_weights"], "device": opts["device"]}
        other = None if handed is not None else _partner_pred(partner, gt)
        if handed is not None:
            out["lpips"] = handed[1]
        elif other is not None:
            from morphgs.metrics.perceptual import lpips_many

            mine, theirs = lpips_many([pred, other], gt, **lp)
            out["lpips"] = np.asarray(mine, dtype=np.float64)
            handoff = (other, np.asarray(theirs, dtype=np.float64))
        else:
            out["lpips"] = np.asarray(M.lpips(pred, gt, reduction="none", **lp), dtype=np.float64)
    depth_gt = None
    if pair.depth_gt is not None:
        depth_gt = _load_depth(pair.depth_gt, "depth_gt", pair.name)
        _same_size(pair, depth_gt[..., None], gt, ("depth_gt", "gt"))
    temporal = [m for m in ("eflow", "ewarp") if m in chosen]
    if temporal and n >= 2:
        step("+".join(temporal))
        flow = valid = None
        if pair.cameras is not None and depth_gt is not None:
            if len(pair.cameras) != n:
                raise EvalError(f"{pair.name}: {len(pair.cameras)} cameras for {n} frames")
            flow, valid = M.geometric_flows(depth_gt, pair.cameras)
        errs = M.temporal_errors(pred, gt, flow=flow, valid=valid, preset=opts["flow_preset"],
                                 epe="eflow" in temporal, warp_error="ewarp" in temporal)
        for key, vals in errs.items():
            out[key] = np.concatenate([[np.nan], vals])
    elif temporal:
        for key in temporal:
            out[key] = np.full(n, np.nan)
    if "depth" in chosen and pair.depth_pred is not None and depth_gt is not None:
        step("depth")
        depth_pred = _load_depth(pair.depth_pred, "depth_pred", pair.name)
        _same_size(pair, depth_pred[..., None], depth_gt[..., None], ("depth_pred", "depth_gt"))
        errs_d = M.depth_metrics(depth_pred, depth_gt, align=opts["depth_align"], reduction="none")
        for key, vals in errs_d.items():
            out[f"depth_{key}"] = np.asarray(vals, dtype=np.float64)
    return out, handoff


def _nanmean(values: Sequence[float] | np.ndarray) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


class _Steps:
    """Counts finished stages on a tqdm bar (or nothing): `begin` names the stage now running."""

    def __init__(self, bar: Any) -> None:
        self.bar = bar
        self.running = False

    def begin(self, what: str) -> None:
        if self.bar is None:
            return
        if self.running:
            self.bar.update(1)
        self.bar.set_postfix_str(what)
        self.running = True

    def finish(self) -> None:
        if self.bar is not None and self.running:
            self.bar.update(1)
        self.running = False

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _progress(total: int | None, enabled: bool) -> Any:
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc="eval", unit="step", file=sys.stderr, dynamic_ncols=True)


def evaluate(
    pairs: Iterable[ClipPair],
    *,
    metrics: Sequence[str] = DEFAULT_METRICS,
    out_dir: str | os.PathLike[str] | None = None,
    lpips_net: str = "alex",
    lpips_weights: str | os.PathLike[str] | None = None,
    depth_align: str | None = None,
    flow_preset: str = "medium",
    device: str = "cpu",
    plots: bool = True,
    progress: bool = True,
    total: int | None = None,
) -> EvalReport:
    """Measure every pair and write the per-frame CSV, the Markdown tables and the plots.

    Args:
        pairs: `ClipPair`s (any iterable, consumed once; clips are read one pair at a time, and
            two consecutive pairs with the same `gt` share its LPIPS features).
        metrics: any of "psnr", "ssim", "lpips", "color_shift", "eflow", "ewarp", "depth"
            ("depth": the seven depth errors, for pairs with both depths).
        out_dir: where to write `per_frame.csv`, `summary.md`, `summary.json` and `plots/`
            (nothing is written when None).
        lpips_net, lpips_weights: LPIPS trunk ("alex" or "vgg") and an explicit weights path.
        depth_align: None, "median" or "lstsq" (see `morphgs.metrics.depth_metrics`).
        flow_preset: DIS preset of the flow metrics.
        device: where LPIPS runs ("cpu", "cuda", ...).
        plots: write one PNG per clip of every metric over the frames (needs matplotlib).
        progress: show a progress bar (tqdm) on stderr.
        total: the number of pairs, for the progress bar, when `pairs` has no len().

    Returns:
        The EvalReport.

    Raises:
        EvalError: an unknown metric, no pairs, clips of different sizes or frame counts.
        MediaError, FileNotFoundError: unreadable or missing clips. LPIPSWeightsError: no LPIPS weights.
    """
    chosen = _check_metrics(metrics)
    opts = {"lpips_net": lpips_net, "lpips_weights": lpips_weights, "depth_align": depth_align,
            "flow_preset": flow_preset, "device": device}
    if "lpips" in chosen:  # fail before any work when the weights are missing
        from morphgs.metrics import lpips_model

        lpips_model(lpips_net, weights=lpips_weights, device=device)
    # the pairs are light (paths or arrays): listed, so a pair can see whether the next one
    # scores against the same target (`eval --run`: input, then output, against one clean clip)
    pair_list = list(pairs)
    if total is None:
        total = len(pair_list)
    stages = sum(m in chosen for m in ("psnr", "ssim", "lpips", "color_shift", "depth")) + any(m in chosen for m in ("eflow", "ewarp"))
    bar = _Steps(_progress(None if total is None else total * stages, progress))
    columns: list[str] = []
    per_clip: list[tuple[ClipPair, dict[str, np.ndarray]]] = []
    try:
        handed: _Handoff | None = None
        for i, pair in enumerate(pair_list):
            def stage(what: str, _name: str = pair.name) -> None:
                bar.begin(f"{_name}: {what}")

            nxt = pair_list[i + 1] if i + 1 < len(pair_list) else None
            partner = nxt if nxt is not None and handed is None and _same_clip(pair.gt, nxt.gt) else None
            values, handed = _clip_metrics(pair, chosen, opts, stage, handed=handed, partner=partner)
            bar.finish()
            per_clip.append((pair, values))
            columns += [k for k in values if k not in columns]
    finally:
        bar.close()
    if not per_clip:
        raise EvalError("no clip pairs to evaluate")
    order = [m for m in METRICS if m in columns]
    report = _tabulate(per_clip, order)
    if out_dir is not None:
        from morphgs.evaluation import report as R

        report.files = R.write_all(report, Path(out_dir), plots=plots, lpips_net=lpips_net)
    return report


def _tabulate(per_clip: list[tuple[ClipPair, dict[str, np.ndarray]]], order: list[str]) -> EvalReport:
    report = EvalReport(metrics=order)
    pooled: dict[str, dict[str, list[float]]] = {}
    for pair, values in per_clip:
        n = max(len(v) for v in values.values())
        for i in range(n):
            row: dict[str, Any] = {"label": pair.label, "clip": pair.name, "frame": i}
            for m in order:
                row[m] = float(values[m][i]) if m in values else math.nan
            report.rows.append(row)
        summary: dict[str, Any] = {"label": pair.label, "clip": pair.name, "frames": n}
        pool = pooled.setdefault(pair.label, {m: [] for m in order})
        for m in order:
            vals = values.get(m, np.full(n, np.nan))
            summary[m] = _nanmean(vals)
            pool[m] += list(vals)
        report.clips.append(summary)
    report.overall = {label: {m: _nanmean(v) for m, v in pool.items()} for label, pool in pooled.items()}
    return report
