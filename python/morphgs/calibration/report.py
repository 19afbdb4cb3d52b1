"""report.md and its plots for `morphgs calibrate` (real vs synthetic PSNR histograms, error
spectra, a sheet of real and calibrated frames side by side)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.calibration.stats import BAND_EDGES

__all__ = ["write_report"]


def _f(v: Any, nd: int = 2) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float) and not np.isfinite(v):
        return "n/a"
    return f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def _plots(folder: Path, name: str, plot: dict[str, Any]) -> list[str]:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from morphgs._core import _write_png

    files = []
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    bins = np.linspace(min(plot["real_psnr"] + plot["synth_psnr"] + plot["real_held_psnr"]) - 0.5,
                       max(plot["real_psnr"] + plot["synth_psnr"] + plot["real_held_psnr"]) + 0.5, 25)
    ax[0].hist(plot["real_held_psnr"], bins=bins, alpha=0.6, label="real")
    ax[0].hist(plot["synth_psnr"], bins=bins, alpha=0.6, label="calibrated synthetic")
    ax[0].set_xlabel("per-frame PSNR (dB)")
    ax[0].legend()
    centres = [float(np.sqrt(a * b)) for a, b in zip(BAND_EDGES, BAND_EDGES[1:])]
    ax[1].semilogx(centres, plot["real_spectrum"], "o-", label="real")
    ax[1].semilogx(centres, plot["synth_spectrum"], "s-", label="calibrated synthetic")
    ax[1].xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax[1].set_xticks(centres, [f"{c:.2g}" for c in centres])
    ax[1].set_xlabel("cycles / pixel (band centres)")
    ax[1].set_ylabel("error / signal (dB)")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(folder / f"{name}-psnr-spectrum.png", dpi=80, metadata={"Software": None})
    plt.close(fig)
    files.append(f"{name}-psnr-spectrum.png")
    if plot["sheet"]:
        rows = [np.concatenate(list(t), axis=1) for t in plot["sheet"]]
        w = max(r.shape[1] for r in rows)
        sheet = np.concatenate([np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0))) for r in rows], axis=0)
        _write_png(folder / f"{name}-sheet.png", np.rint(np.clip(sheet, 0, 1) * 255).astype(np.uint8))
        files.append(f"{name}-sheet.png")
    return files


def _family_sheet(folder: Path, regime: str, results: Sequence[dict[str, Any]],
                  plots: Sequence[dict[str, Any]]) -> str | None:
    """One contact sheet of a regime's families: per held-out pair (rows), its middle frame clean,
    real corrupted, then each family's calibrated synthetic frame of the same camera and seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from morphgs.curation.sources import slug

    pairs = min(len(p["sheet"]) for p in plots)
    if pairs == 0:
        return None
    cols = ["clean", f"real {regime}"] + [r["family"] for r in results]
    h, w = plots[0]["sheet"][0][0].shape[:2]
    scale = 1.6 / w * 100
    fig, axes = plt.subplots(pairs, len(cols), figsize=(len(cols) * w * scale / 100 + 0.2, pairs * h * scale / 100 + 0.4),
                             squeeze=False)
    for i in range(pairs):
        frames = [plots[0]["sheet"][i][0], plots[0]["sheet"][i][1]] + [p["sheet"][i][2] for p in plots]
        for j, f in enumerate(frames):
            ax = axes[i][j]
            ax.imshow(np.clip(f, 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=7)
    fig.tight_layout(pad=0.2)
    name = f"{slug(regime)}-families.png"
    fig.savefig(folder / name, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return name


def _mix_lines(doc: dict[str, Any]) -> list[str]:
    """The op-mix search's tables (one per result that ran it)."""
    runs = [r for r in doc["results"] if r.get("mix_search") and r["mix_search"].get("objective") != "realism"]
    if not runs:
        return _realism_search_lines(doc)
    lines = ["", "## Op mix search", "",
             "Each mix (the ops' weights; op k runs at n w_k times the strength) matched pair by pair to the real "
             "PSNR on the calibration scenes, then compared with the real pairs on the other statistics: W1 over "
             "pairs / the IQR of the real and every mix's values pooled; the score is their mean. The chosen mix "
             "(lowest score among those reaching the real median) is calibrated above.", ""]
    for r in runs:
        m = r["mix_search"]
        groups = sorted({g for c in m["candidates"] for g in c["distances"]})
        lines += [f"### {r['family']} / {r['regime']} (scenes {', '.join(m['scenes'])})", "",
                  "| mix | median strength | " + " | ".join(groups) + " | score |",
                  "|---|---|" + "---|" * len(groups) + "---|"]
        for i, c in enumerate(m["candidates"]):
            w = ", ".join(f"{k} {v:.2f}" for k, v in c["weights"].items())
            tags = [t for t, on in (("chosen", i == m["chosen"]), ("preset", i == m["preset"])) if on]
            name = f"{w}" + (f" (**{', '.join(tags)}**)" if tags else "")
            med = _f(c["median_strength"], 3) if c["reachable"] else "unreachable"
            lines.append(f"| {name} | {med} | " + " | ".join(_f(c["distances"].get(g)) for g in groups)
                         + f" | {_f(c['score'], 3)} |")
        lines.append("")
    return lines + _realism_search_lines(doc)


def _realism_search_lines(doc: dict[str, Any]) -> list[str]:
    """The realism search's trials (one table per result that ran it)."""
    runs = [r for r in doc["results"] if (r.get("mix_search") or {}).get("objective") == "realism"]
    if not runs:
        return []
    lines = ["", "## Realism search", "",
             "Each trial (Optuna TPE, seeded per trial) an op mix (op k at n w_k times the strength) and, for the "
             "camera ops, the virtual training views' spacing; matched pair by pair to the real PSNR on the "
             "calibration scenes, then scored by the cross-fitted AUC of the CNN classifier between its pairs and "
             "the real ones plus 0.001 x its separation d' (the held-out logits' gap in pooled standard deviations, "
             "clipped to [0, 10]: it ranks mixes the AUC calls equal; unreachable mixes score 1.02 + shortfall / 10 "
             "dB). The lowest wins and is calibrated above.", ""]
    for r in runs:
        m = r["mix_search"]
        lines += [f"### {r['family']} / {r['regime']}", "",
                  "| trial | mix | train_every | median strength | AUC (cross-fitted) | d' |", "|---|---|---|---|---|---|"]
        for i, t in enumerate(m["trials"]):
            w = ", ".join(f"{k} {v:.2f}" for k, v in t["weights"].items())
            tag = " (**chosen**)" if i == m["chosen"] else ""
            med = _f(t["median_strength"], 3) if t["reachable"] else "unreachable"
            lines.append(f"| {t['trial'] + 1}{tag} | {w} | {t['train_every']} | {med} | {_f(t['auc'], 3)} | {_f(t.get('separation', float('nan')), 2)} |")
        lines.append("")
    return lines


def _realism_lines(doc: dict[str, Any]) -> list[str]:
    """The CNN two-sample test of every result that ran it."""
    runs = [r for r in doc["results"] if r.get("realism")]
    if not runs:
        return []
    lines = ["", "## Realism: can a classifier tell them apart?", "",
             "A small CNN on each frame's clean render and residual, trained on the calibration scenes' real and "
             "synthetic pairs, scores the held-out scenes' frames (cross-fitted in two folds when there is one "
             "scene). AUC 0.5: it cannot tell synthetic from real; 1.0: it always can. 95% bootstrap interval over "
             "scenes (pairs with one scene). Floor: the same network asked to tell two halves of the real pairs "
             "apart. \"indistinguishable\": the interval's lower end at or below the floor's upper end. d': the "
             "network's separation of the two (synthetic minus real mean logit over their pooled standard "
             "deviation; it still ranks families when every AUC is 1.00).", "",
             "| family | regime | AUC [95% CI] | d' | floor AUC [95% CI] | frames real / synthetic | indistinguishable |",
             "|---|---|---|---|---|---|---|"]
    for r in runs:
        c, f = r["realism"]["classifier"], r["realism"]["floor"] or {}
        fci = f.get("ci", [None, None])
        lines.append(f"| {r['family']} | {r['regime']} | {_f(c['auc'])} [{_f(c['ci'][0])}, {_f(c['ci'][1])}] | "
                     f"{_f(c.get('separation'))} | {_f(f.get('auc'))} [{_f(fci[0])}, {_f(fci[1])}] | {c['frames']['real']} / "
                     f"{c['frames']['synthetic']} | {'yes' if r['realism']['indistinguishable'] else 'no'} |")
    return lines + [""]


def _ranking_lines(doc: dict[str, Any]) -> list[str]:
    """The families of each regime with two or more, from the most to the least like the real
    pairs (calibration.json's `ranking`)."""
    lines: list[str] = []
    for regime, entries in doc.get("ranking", {}).items():
        if len(entries) < 2:
            continue
        lines += [f"**Closest to the real {regime} pairs first** (matched ones, then by AUC, then by d', then by the "
                  "furthest statistic's distance beyond its floor):", "",
                  "| rank | family | AUC | d' | furthest off (IQR beyond its floor) | matched |", "|---|---|---|---|---|---|"]
        for i, e in enumerate(entries, 1):
            lines.append(f"| {i} | {e['family']} | {_f(e['auc'])} | {_f(e.get('separation'))} | `{e['furthest']}` ({_f(e['furthest_excess'])}) | "
                         f"{'yes' if e['matched'] else 'no'} |")
        lines.append("")
    return lines


def write_report(out: Path, doc: dict[str, Any], plot_data: Sequence[dict[str, Any]], *, plots: bool = True) -> None:
    """Write out/report.md (and out/plots/*.png when `plots`)."""
    lines = ["# morphgs calibrate report", "",
             f"Scenes: {', '.join(doc['scenes'])}. Regimes: {', '.join(doc['regimes'])}. "
             f"Families: {', '.join(doc['families'])}. Frames per pair {', '.join(map(str, doc['frames']))}, "
             f"{doc['resolution'][0]}x{doc['resolution'][1]}, seed {doc['seed']}."
             + "".join(f" {k}: sparse fits of {v} steps." for k, v in doc.get("fit_steps", {}).items() if v), "",
             "## Strength search", "",
             "| family | regime | real median PSNR | monotone | reachable | median strength (PSNR) "
             "| most severe reached | unreachable pairs | strength quantiles (over pairs) p5 / p50 / p95 | config |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["results"]:
        s = r["search"]
        q = dict(zip(s["quantiles"]["p"], s["quantiles"]["strength"]))
        med = (f"{s['median_strength']:.4g} ({s['median_psnr_reached']:.2f} dB)" if s["reachable"]
               else "**unreachable**")
        lines.append(f"| {r['family']} | {r['regime']} | {s['target_median_psnr']:.2f} dB | "
                     f"{'yes' if s['monotone'] else '**no**'} | {'yes' if s['reachable'] else '**no**'} | {med} | "
                     f"{s['most_severe_psnr']:.2f} dB at s={s['most_severe_strength']:.4g} | "
                     f"{100 * s['unreachable_frames']:.0f}% | {q[0.05]:.3g} / {q[0.5]:.3g} / {q[0.95]:.3g} | "
                     f"`{r['config_file']}` |")
    for r in doc["results"]:
        s = r["search"]
        if not s["monotone"]:
            steps = "; ".join(f"s {v['from_strength']:.3g} -> {v['to_strength']:.3g}: {v['from_psnr']:.2f} -> "
                              f"{v['to_psnr']:.2f} dB" for v in s["violations"])
            lines += ["", f"**{r['family']} / {r['regime']}: severity does not rise monotonically with strength** "
                          f"({steps}); frames are matched on the running minimum of their curves."]
        if s.get("below_grid_frames", 0.0) > 0:
            lines += ["", f"{r['family']} / {r['regime']}: {100 * s['below_grid_frames']:.0f}% of the real frames are milder "
                          f"than the smallest strength scanned (s = {s['grid'][0]:.4g}); they get that strength."]
        if not s["reachable"]:
            lines += ["", f"**{r['family']} / {r['regime']} is unreachable**: the real median is "
                          f"{s['target_median_psnr']:.2f} dB, the family reaches at most "
                          f"{s['most_severe_psnr']:.2f} dB (s = {s['most_severe_strength']:.4g}). Its config uses the "
                          "most severe strength for the pairs it cannot reach."]
    lines += ["", "## Each op's share of the error", "",
              "MSE of each op alone at the median strength (the most severe one when unreachable), as a share of "
              "their sum.", "", "| family | regime | strength | shares |", "|---|---|---|---|"]
    for r in doc["results"]:
        sh = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["op_shares"].items())
        lines.append(f"| {r['family']} | {r['regime']} | {r['op_shares_strength']:.4g} | {sh} |")
    lines += _mix_lines(doc)
    lines += _realism_lines(doc)
    lines += ["", "## Goodness of fit", "",
              "Distances: W1 / IQR of the real values per statistic. Classifier: out-of-fold AUC of a logistic "
              "regression on every statistic (0.5 = indistinguishable), 95% bootstrap interval. Floor: the same "
              "between two halves of the real pairs (by scene). \"matched\" only within that floor: every distance at most "
              "its floor + 0.5 and the AUC interval reaching the floor's.", ""]
    lines += _ranking_lines(doc)
    for r in doc["results"]:
        g = r["goodness"]
        where = (f"held-out scene(s) {', '.join(g['scenes'])}" if g["held_out"]
                 else f"in-sample (one scene, {', '.join(g['scenes'])}: no held-out scene)")
        c, f = g["classifier"], g["floor"]
        verdict = ("**matched** (within the real-vs-real floor)" if g["matched"]
                   else "**not matched**")
        verdict += f"; furthest off: `{g['furthest']}` ({_f(g['furthest_excess'])} IQR beyond its floor)"
        lines += [f"### {r['family']} / {r['regime']}", "",
                  f"On {where}, {g['pairs']['real']} real and {g['pairs']['synthetic']} synthetic pairs: AUC "
                  f"{_f(c['auc'])} [{_f(c['ci'][0])}, {_f(c['ci'][1])}] ({c['bootstrap']} bootstrap); floor AUC "
                  f"{_f(f['auc'])} [{_f(f['ci'][0])}, {_f(f['ci'][1])}] (halves by {f['split']}). {verdict}.", "",
                  "| statistic | real median | synthetic median | distance | floor |", "|---|---|---|---|---|"]
        for n, d in g["distances"].items():
            rm, sm = g["medians"].get(n, [None, None])
            lines.append(f"| {n} | {_f(rm, 3)} | {_f(sm, 3)} | {_f(d)} | {_f(f['distances'].get(n))} |")
        lines.append("")
    if plots:
        folder = out / "plots"
        folder.mkdir(parents=True, exist_ok=True)
        lines += ["## Plots", ""]
        for regime in doc["regimes"]:
            idx = [i for i, r in enumerate(doc["results"]) if r["regime"] == regime]
            if len(idx) >= 2:
                sheet = _family_sheet(folder, regime, [doc["results"][i] for i in idx], [plot_data[i] for i in idx])
                if sheet:
                    lines += [f"### Every family against the real {regime} pairs", "",
                              "Middle frames of the held-out pairs: clean, real corrupted, then each family's "
                              "calibrated synthetic frame from the same camera and seed:", "",
                              f"![](plots/{sheet})", ""]
        for r, pd in zip(doc["results"], plot_data):
            name = Path(r["config_file"]).stem  # the plots are named as the result's config file
            files = _plots(folder, name, pd)
            lines += [f"### {r['family']} / {r['regime']}", "",
                      "PSNR histograms (real held-out vs calibrated synthetic) and error spectra:", "",
                      f"![]({'plots/' + files[0]})", ""]
            if len(files) > 1:
                lines += ["Middle frames, per pair: clean | real corrupted | calibrated synthetic:", "",
                          f"![]({'plots/' + files[1]})", ""]
    (out / "report.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
