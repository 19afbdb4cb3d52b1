"""Stage 8, the report: results.json / results.csv (every per-clip value), table.md in the paper's
Table 1 layout (morphgs.ablation.table) and plots/ (morphgs.ablation.plots: paired differences
with CIs, CKA against step, a qualitative sheet), from the finished outputs of the other stages.
The notes summarise each calibration (stages/calibration.py) and say where the geometry's ground
truth comes from.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from morphgs.ablation.conditions import Condition
from morphgs.ablation.table import format_table

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "calibration_note", "clean_fit_note", "gather", "make",
           "sparse_fit_note"]

VERSION = 5  # 2: deltas.png; 3: the clean fits of captures; 4: each regime's input PSNR; 5: sparse-fit convergence
IGNORE: tuple[str, ...] = ()
RESUMABLE = False


def gather(parts: Sequence[tuple[str, str, dict[str, Any]]]) -> dict[str, Any]:
    """Per-clip records, severities and CKA curves from the finished stage outputs, given as
    (stage, output folder, meta) triples."""
    recs: dict[tuple[Any, ...], dict[str, Any]] = {}
    severity: dict[str, float] = {}
    calibration: dict[str, dict[str, Any]] = {}
    cka: list[dict[str, Any]] = []
    clean_fits: dict[str, dict[str, Any]] = {}
    fits: dict[str, dict[str, Any]] = {}
    for stage, path, meta in parts:
        p = Path(path)
        if stage == "testsets":
            conv = json.loads((p / "testset.json").read_text()).get("convergence")
            if conv is not None:
                fits.setdefault(meta["regime"], {})[meta["scene"]] = conv
        elif stage == "cleanfits":
            info = json.loads((p / "cleanfit.json").read_text())
            clean_fits[meta["scene"]] = {**{k: info[k] for k in ("heldout_psnr", "heldout_ssim", "steps",
                                                                  "gaussians", "photos", "heldout_views")},
                                         "min_psnr": meta["min_psnr"]}
        elif stage == "calibration":
            calibration[meta["condition"]] = json.loads((p / "summary.json").read_text())
        elif stage == "trainsets":
            severity[meta["condition"]] = json.loads((p / "severity.json").read_text())["psnr_mean"]
        elif stage == "training":
            cka.append({"condition": meta["condition"], "seed": meta["seed"],
                        **json.loads((p / "cka.json").read_text())})
        elif stage in ("metrics2d", "metrics3d"):
            data = json.loads((p / f"{stage}.json").read_text())
            for clip, vals in data["clips"].items():
                k = (meta["regime"], meta["condition"], meta["seed"], meta["scene"], clip)
                rec = recs.setdefault(k, {"regime": k[0], "condition": k[1], "seed": k[2], "scene": k[3], "clip": k[4]})
                rec.update(vals)
    records = sorted(recs.values(), key=lambda r: (r["regime"], r["condition"], str(r["seed"]), r["scene"], r["clip"]))
    return {"records": records, "severity": dict(sorted(severity.items())),
            "calibration": dict(sorted(calibration.items())), "clean_fits": dict(sorted(clean_fits.items())),
            "sparse_fits": {r: dict(sorted(v.items())) for r, v in sorted(fits.items())},
            "cka": sorted(cka, key=lambda c: (c["condition"], c["seed"]))}


def calibration_note(condition: str, c: dict[str, Any]) -> str:
    """One line on a calibrated condition: what it was matched to and what it reached."""
    cond = Condition.parse(condition)
    reg = cond.regime
    if c["reachable"]:
        med = f"median strength {c['median_strength']:.3g} ({c['median_psnr_reached']:.2f} dB)"
    else:
        med = f"UNREACHABLE (most severe {c['most_severe_psnr']:.2f} dB)"
    fit = "matched" if c.get("matched") else f"not matched (furthest: {c.get('furthest')})"
    auc = c.get("auc")
    if isinstance(auc, (int, float)) and auc == auc:
        floor = c.get("floor_auc")
        sep = c.get("separation")
        fit += f"; classifier AUC {auc:.2f}"
        if isinstance(sep, (int, float)) and sep == sep:
            fit += f", d' {sep:.2f}"
        if isinstance(floor, (int, float)) and floor == floor:
            fit += f" (real-vs-real floor {floor:.2f})"
    return (f"{cond.label}: {c['family']} calibrated against target-{reg}'s real pairs "
            f"(median {c['real_median_psnr']:.2f} dB): {med}; strength p5/p50/p95 {c['strength_p05']:.3g} / {c['strength_p50']:.3g} / {c['strength_p95']:.3g}"
            f"{'' if c['monotone'] else '; severity not monotone in strength'}; held-out goodness of fit: {fit} "
            "(calibration/<condition>/calib/report.md).")


def clean_fit_note(fits: dict[str, dict[str, Any]]) -> list[str]:
    """The clean fits of captures given as photos: each one's held-out quality, and the poor ones
    (held-out PSNR below the study's clean.min_psnr) named."""
    if not fits:
        return []
    parts = [f"{s} {f['heldout_psnr']:.2f} dB / SSIM {f['heldout_ssim']:.3f} ({f['photos']} photos, "
             f"{f['heldout_views']} held out, {f['steps']} steps, {f['gaussians']} Gaussians)" for s, f in fits.items()]
    out = ["Clean scenes fitted from the captures' photos, held-out PSNR: " + "; ".join(parts) + "."]
    poor = [s for s, f in fits.items() if f["heldout_psnr"] is None or f["heldout_psnr"] < f["min_psnr"]]
    if poor:
        lim = next(iter(fits.values()))["min_psnr"]
        out.append(f"POOR clean fit (held-out PSNR below clean.min_psnr = {lim:g} dB): {', '.join(poor)}; "
                   "their training pairs' clean side and the geometry reference are renders of a poor scene.")
    return out


def sparse_fit_note(fits: dict[str, dict[str, Any]]) -> list[str]:
    """Per regime, the test sets' sparse fits: their length and how their held-out PSNR moved over
    the last quarter of it (median over the test scenes; flat within 0.2 dB counts as converged)."""
    import statistics

    out = []
    for rg, per in fits.items():
        gains = [c["last_quarter_gain_db"] for c in per.values() if c.get("last_quarter_gain_db") is not None]
        steps = sorted({c["steps"] for c in per.values()})
        if not gains:
            continue
        g = statistics.median(gains)
        ends = [c["psnr_by_step"][-1][1] for c in per.values() if c.get("psnr_by_step")]
        state = "flat: converged" if abs(g) < 0.2 else ("still rising: longer fits would change the inputs"
                                                         if g > 0 else "falling: the fits overfit their views")
        out.append(f"{rg} sparse fits: {'/'.join(map(str, steps))} steps; held-out capture views at "
                   f"{statistics.median(ends):.2f} dB (median of {len(ends)} test scene(s)), {g:+.2f} dB over the "
                   f"last quarter ({state}).")
    return out


def _csv(records: Sequence[dict[str, Any]]) -> str:
    keys = ["regime", "condition", "seed", "scene", "clip"]
    extra = sorted({k for r in records for k in r} - set(keys))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(keys + extra)
    for r in records:
        w.writerow(["" if r.get(k) is None else r.get(k) for k in keys + extra])
    return buf.getvalue()


def make(work: Path, *, parts: Sequence[tuple[str, str, dict[str, Any]]], conditions: Sequence[str],
         regimes: Sequence[str], lpips_note: str | None) -> None:
    """table.md, results.json, results.csv and plots/ of the outputs in `parts` ((stage, folder,
    meta) of every trainsets, calibration, training, testsets, refine and metrics job)."""
    from morphgs.ablation import plots

    g = gather(parts)
    notes = []
    if lpips_note:
        notes.append(f"LPIPS columns read n/a: {lpips_note}.")
    notes += clean_fit_note(g["clean_fits"])
    notes += sparse_fit_note(g["sparse_fits"])
    notes += [calibration_note(c, v) for c, v in g["calibration"].items()]
    notes.append("Geometry ground truth: depth of the clean dense 3DGS at the clip cameras, unprojected where "
                 "alpha >= 0.5, in units of the clean scene's bbox diagonal (docs/ablation.md)"
                 + (": for captures of photos, their clean fit's depth; the 2D metrics and the re-fit's held-out "
                    "frames are scored against the photos." if g["clean_fits"] else "."))
    (work / "table.md").write_text(format_table(g["records"], regimes=regimes, conditions=conditions,
                                                severity=g["severity"], notes=notes), encoding="utf-8")
    (work / "results.json").write_text(json.dumps({"records": g["records"], "severity": g["severity"],
                                                   "calibration": g["calibration"], "clean_fits": g["clean_fits"],
                                                   "sparse_fits": g["sparse_fits"],
                                                   "cka": g["cka"], "lpips_note": lpips_note},
                                                  indent=1, sort_keys=True) + "\n", encoding="utf-8")
    (work / "results.csv").write_text(_csv(g["records"]), encoding="utf-8")
    plots.write_all(work / "plots", g, regimes=regimes, conditions=conditions, parts=parts)
