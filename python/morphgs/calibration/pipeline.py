"""The calibration itself, on real pairs already read and scenes already loaded
(docs/calibration.md): per regime, its scenes split into calibration and held-out ones; per
family, the optional op-mix search, the strength search, each op's share of the error and the
goodness of fit. `calibrate_pairs` writes nothing and returns plain data; `morphgs.calibration.run`
is the command around it (real pairs made or read, outputs written) and
`morphgs.calibration.outputs` writes what it returns.

Each real pair's statistics (`stats.pair_stats`) are computed once per regime and shared by the
strength search (its per-frame PSNR), the op-mix search and the goodness of fit of every family.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.calibration import goodness, stats
from morphgs.calibration.mix import mix_distances, mixed, simplex_grid
from morphgs.calibration.objective import OBJECTIVES, TRIALS, realism_search
from morphgs.calibration.pairs import Bench, CalibrationError, RealPair
from morphgs.calibration.realism import STEPS, Clip, classifier_test, floor_test
from morphgs.calibration.search import DEFAULT_GRID, search
from morphgs.strength import FAMILIES, Blur2d, Strength, draw_strength

__all__ = ["ALL_FAMILIES", "Calibration", "calibrate_pairs", "expand_families", "parse_family", "rank_families",
           "split_scenes"]

#: What `--family all` stands for: every strength family and the 2D blur.
ALL_FAMILIES: tuple[str, ...] = (*FAMILIES, Blur2d.family)


def parse_family(spec: str) -> tuple[str, Strength | Blur2d]:
    """A --family: a family name (its ops at the preset's proportions), blur2d (strength = sigma
    in pixels) or a JSON file {"family", "ops"} fixing the ops and their proportions; (label, base
    config at strength 1).

    Raises:
        CalibrationError: an unknown family, an unreadable file or a bad op (naming --family).
    """
    if spec == Blur2d.family:
        return spec, Blur2d()
    if spec.lower().endswith(".json"):
        path = Path(spec)
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise CalibrationError(f"--family {spec}: cannot read JSON ({e})") from None
        if not isinstance(d, dict):
            raise CalibrationError(f"--family {spec}: expected a JSON object {{\"family\", \"ops\"}}")
        try:
            cfg = Strength.from_dict({k: v for k, v in d.items() if k not in ("strength", "quantiles")})
        except (TypeError, ValueError) as e:
            raise CalibrationError(f"--family {spec}: {e}") from None
        return path.stem, cfg.at(1.0)
    if spec not in FAMILIES:
        raise CalibrationError(f"--family {spec}: unknown family; valid families: {', '.join(FAMILIES)}, "
                               f"{Blur2d.family} (or a JSON file {{\"family\", \"ops\"}})")
    return spec, Strength(spec)


def expand_families(families: Sequence[str]) -> list[str]:
    """`families` with "all" replaced by `ALL_FAMILIES` (those not already named), order kept."""
    out: list[str] = []
    for f in families:
        for g in (ALL_FAMILIES if f == "all" else (f,)):
            if g not in out or f != "all":
                out.append(g)
    return out


def split_scenes(pairs: Sequence[RealPair]) -> tuple[list[RealPair], list[RealPair]]:
    """(calibration pairs, held-out pairs): scenes in sorted order alternate; with one scene the
    same pairs serve both (the goodness of fit is then in-sample, and says so) and the held-out
    list is empty."""
    scenes = sorted({p.scene for p in pairs})
    if len(scenes) < 2:
        return list(pairs), []
    held = set(scenes[1::2])
    return [p for p in pairs if p.scene not in held], [p for p in pairs if p.scene in held]


def rank_families(results: Sequence[Mapping[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per regime, the families ordered from the most to the least like the real pairs on the
    held-out scenes: matched ones first, then by the classifier's AUC (0.5 = indistinguishable),
    then by its separation d' (the CNN's; it ranks families the AUC calls equal, e.g. all at
    1.00), then by how far the furthest statistic lies beyond its real-vs-real floor, then by
    name (so the order is the same on every run). Each entry: family, auc, separation (None
    without the CNN test), furthest, furthest_excess, matched. The AUC is the CNN two-sample test's (`realism`) where it ran, else the logistic
    regression's on the statistics (`goodness`); `auc_kind` says which."""
    by_regime: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        g = r["goodness"]
        cnn = (r.get("realism") or {}).get("classifier")
        auc = cnn["auc"] if cnn else g["classifier"]["auc"]
        by_regime.setdefault(r["regime"], []).append({
            "family": r["family"], "auc": auc, "auc_kind": "cnn" if cnn else "statistics",
            "separation": cnn.get("separation") if cnn else None, "furthest": g["furthest"],
            "furthest_excess": g["furthest_excess"], "matched": bool(g["matched"])})

    def finite(v: Any) -> tuple[bool, float]:  # missing or NaN values sort last
        ok = isinstance(v, (int, float)) and math.isfinite(v)
        return (not ok, float(v) if ok else 0.0)

    def key(e: dict[str, Any]) -> tuple[Any, ...]:
        return (not e["matched"], *finite(e["auc"]), *finite(e["separation"]), *finite(e["furthest_excess"]),
                e["family"])

    return {k: sorted(v, key=key) for k, v in by_regime.items()}


@dataclass(frozen=True)
class Calibration:
    """What `calibrate_pairs` found.

    Attributes:
        regimes: the regimes, in the order given. families: the family labels, in order.
        frames: the real pairs' frame counts (sorted, distinct). resolution: [width, height].
        search_mix: whether the op mix was searched.
        results: per (regime, family), regime-major, calibration.json's result (plain JSON data;
            `outputs.document` adds its config file's name).
        plots: per result, what report.md's plots draw (PSNR and spectra, a sheet of frames).
        costs: per result, the family's cost per pair at its calibrated strength, measured on
            the goodness-of-fit pairs: {"family", "regime", "pairs", "perturb", "render",
            "seconds_per_pair"} (wall seconds per pair, this machine; kept out of `results`,
            so that calibration.json is the same bytes on every run).
    """

    regimes: list[str]
    families: list[str]
    frames: list[int]
    resolution: list[int]
    search_mix: bool
    objective: str
    results: list[dict[str, Any]]
    plots: list[dict[str, Any]]
    costs: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class _Side:
    """Real pairs of one side of a regime's split, their statistics and their synthetic bench."""

    pairs: list[RealPair]
    stats: list[dict[str, Any]]
    bench: Bench

    def clips(self) -> list[Clip]:
        """The real pairs as the realism classifier's clips (label 0)."""
        return [Clip(p.corrupted, p.clean, p.scene, 0) for p in self.pairs]


@dataclass(frozen=True)
class Options:
    """How `calibrate_pairs` searches and judges (see its Args)."""

    grid: Sequence[float] = DEFAULT_GRID
    lpips: bool = False
    search_mix: bool = False
    mix_steps: int = 3
    objective: str = "psnr"
    trials: int = TRIALS
    realism_steps: int = STEPS
    search_steps: int = STEPS // 2
    repeats: int = 1
    seed: int = 0
    state_dir: Path | None = None


def calibrate_pairs(groups: Mapping[str, Sequence[RealPair]], scenes: Mapping[str, Any],
                    families: Sequence[tuple[str, Strength | Blur2d]], *, grid: Sequence[float] = DEFAULT_GRID,
                    lpips: bool = False, search_mix: bool = False, mix_steps: int = 3, objective: str = "psnr",
                    trials: int = TRIALS, realism_steps: int = STEPS, search_steps: int = STEPS // 2, repeats: int = 1,
                    seed: int = 0, state_dir: str | Path | None = None,
                    say: Callable[[str], None] | None = None) -> Calibration:
    """Calibrate each family's strength distribution to each regime's real pairs; writes nothing
    but the realism search's state files (under `state_dir`, when given).

    Args:
        groups: regime -> its real pairs (`pairs.read_real_pairs`, `pairs.by_regime`), one size.
        scenes: scene id -> clean GaussianScene, for every pair's scene.
        families: (label, base config at strength 1) per family (`parse_family`), distinct labels.
        grid: the strength scan's log grid. lpips: also compute LPIPS (where installed).
        search_mix, mix_steps: also search each family's op mix (families of two or more ops) on a
            simplex grid of weights in multiples of 1/mix_steps (`morphgs.calibration.mix`).
        objective: "psnr" (match the PSNR; with `search_mix`, the mix closest on the statistics)
            or "realism" (the op mix of families of two or more ops searched to minimise the CNN
            classifier's AUC, `morphgs.calibration.objective`, `trials` candidates, its classifier
            trained `search_steps` steps per fold, its state files under `state_dir`).
        realism_steps: training steps of the CNN two-sample test reported for every family on the
            held-out scenes, with its real-vs-real floor per regime (0: not run).
        repeats: networks per fold of every classifier (the test, its floor and the search's),
            their logits averaged (`realism.classifier_test`): steadier AUCs at `repeats` times
            the classifier's cost.
        seed: the classifiers' and the search's seed.
        say: progress messages (none when None).

    Raises:
        CalibrationError: no real pairs, pairs of mismatched sizes, a pair's scene not in `scenes`,
            an unknown objective, repeats < 1.
    """
    say = say or (lambda m: None)
    if objective not in OBJECTIVES:
        raise CalibrationError(f"--objective {objective}: unknown; valid objectives: {', '.join(OBJECTIVES)}")
    if repeats < 1:
        raise CalibrationError(f"--realism-repeats must be >= 1, got {repeats}")
    opts = Options(grid=grid, lpips=lpips, search_mix=search_mix, mix_steps=mix_steps, objective=objective,
                   trials=trials, realism_steps=realism_steps, search_steps=search_steps, repeats=repeats,
                   seed=seed, state_dir=Path(state_dir) if state_dir is not None else None)
    sizes = {p.clean.shape[1:3] for ps in groups.values() for p in ps}
    if not sizes:
        raise CalibrationError("no real pairs to calibrate against")
    if len(sizes) > 1:
        raise CalibrationError(f"real pairs of mismatched sizes {sorted(sizes)}: calibrate one size at a time")

    def side(ps: list[RealPair]) -> _Side:
        return _Side(ps, [stats.pair_stats(p.corrupted, p.clean, lpips=lpips) for p in ps], Bench(scenes, ps))

    results, plots, costs = [], [], []
    for regime, pairs in groups.items():
        calib, held = split_scenes(pairs)
        calib_side, held_side = side(calib), (side(held) if held else None)
        floor = None
        if realism_steps > 0:
            t0 = time.perf_counter()
            floor = floor_test(calib_side.clips(), held_side.clips() if held_side else None, seed=seed,
                               steps=realism_steps, repeats=repeats)
            say(f"calibrate: {regime}: real-vs-real classifier floor AUC {floor['auc']:.3f} "
                f"[{time.perf_counter() - t0:.1f} s]")
        for label, base in families:
            result, plot, cost = _calibrate_one(label, base, regime, calib_side, held_side, opts, floor, say=say)
            results.append(result)
            plots.append(plot)
            costs.append(cost)
    return Calibration(regimes=list(groups), families=[label for label, _ in families],
                       frames=sorted({len(p.clean) for ps in groups.values() for p in ps}),
                       resolution=[int(v) for v in next(iter(sizes))[::-1]], search_mix=search_mix,
                       objective=objective, results=results, plots=plots, costs=costs)


def _search_mix(label: str, base: Strength, calib: _Side, real_psnr: np.ndarray, pair_of_frame: np.ndarray, *,
                steps: int, grid: Sequence[float], lpips: bool, say: Callable[[str], None]) -> tuple[Strength, dict[str, Any]]:
    """The op-mix search (morphgs.calibration.mix) on the calibration pairs: each candidate mix
    matched pair by pair to the real PSNR (a scan at one point per octave of `grid`, then
    interpolation), its pairs compared with the real ones on the other statistics; the mix of
    lowest score among those that reach the real median wins. Returns (chosen config, report)."""
    t0 = time.perf_counter()
    coarse = list(grid)[::2] if len(grid) >= 6 else list(grid)
    bench = calib.bench
    rows: list[dict[str, Any]] = []
    synth_all = []
    for w in simplex_grid(list(base.base), steps):
        cfg = mixed(base, w)

        def measure(s: float, c: Strength = cfg) -> np.ndarray:
            return bench.frame_psnr(c.at(s))

        res = search(measure, real_psnr, grid=coarse, pairs=pair_of_frame, iters=6, tol_db=0.1)
        synth = [stats.pair_stats(bench.corrupted(cfg.at(s), k), bench.clean[k], lpips=lpips)
                 for k, s in enumerate(res.pair_strengths)]
        synth_all.append(synth)
        rows.append({"weights": w, "ops": cfg.base, "reachable": res.reachable,
                     "median_strength": res.median_strength, "median_psnr_reached": res.median_psnr_reached,
                     "pair_strengths": res.pair_strengths})
    for row, d in zip(rows, mix_distances(calib.stats, synth_all)):
        row.update(d)
    pool = [i for i, r in enumerate(rows) if r["reachable"]] or list(range(len(rows)))
    best = min(pool, key=lambda i: (rows[i]["score"] if np.isfinite(rows[i]["score"]) else np.inf, i))
    chosen: dict[str, float] = rows[best]["weights"]
    say(f"calibrate: {label}: op mix {', '.join(f'{k} {v:.2f}' for k, v in chosen.items())} chosen of {len(rows)} "
        f"(score {rows[best]['score']:.3f}; the preset's {rows[0]['score']:.3f}) [{time.perf_counter() - t0:.1f} s]")
    info = {"steps": steps, "grid": coarse, "candidates": rows, "chosen": best, "preset": 0,
            "scenes": sorted({p.scene for p in calib.pairs})}
    return mixed(base, chosen), info


def _calibrate_one(label: str, base: Strength | Blur2d, regime: str, calib: _Side, held: _Side | None, opts: Options,
                   floor: dict[str, Any] | None, *,
                   say: Callable[[str], None]) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """One family against one regime: (calibration.json's result, its plot data, its cost per pair)."""
    family = base.family
    grid, lpips = opts.grid, opts.lpips
    pairs, bench = calib.pairs, calib.bench
    real_psnr = np.concatenate([np.asarray(st["frame_psnr"], dtype=np.float64) for st in calib.stats])
    pair_of_frame = np.concatenate([np.full(len(p.clean), k) for k, p in enumerate(pairs)])
    mix_info = None
    if isinstance(base, Strength) and len(base.base) >= 2:
        if opts.objective == "realism":
            from morphgs.curation.sources import slug

            state = (opts.state_dir / f"{slug(regime)}--{slug(label)}.jsonl") if opts.state_dir is not None else None
            base, mix_info = realism_search(label, base, bench, calib.clips(), real_psnr, pair_of_frame,
                                            real_ids=[p.pair_id for p in pairs], grid=grid, trials=opts.trials,
                                            seed=opts.seed, steps=opts.search_steps, repeats=opts.repeats,
                                            state=state, say=say)
        elif opts.search_mix:
            base, mix_info = _search_mix(label, base, calib, real_psnr, pair_of_frame, steps=opts.mix_steps,
                                         grid=grid, lpips=lpips, say=say)
    t0 = time.perf_counter()
    res = search(lambda s: bench.frame_psnr(base.at(s)), real_psnr, grid=grid, pairs=pair_of_frame)
    say(f"calibrate: {label} vs {regime}: real median {res.target_median_psnr:.2f} dB; "
        + (f"median strength {res.median_strength:.4g} ({res.median_psnr_reached:.2f} dB)" if res.reachable
           else f"UNREACHABLE (most severe {res.most_severe_psnr:.2f} dB at s={res.most_severe_strength:.4g})")
        + ("" if res.monotone else "; severity NOT monotone in strength")
        + f" [{time.perf_counter() - t0:.1f} s]")
    s_ref = res.median_strength if res.median_strength is not None else res.most_severe_strength
    mses = {op: bench.frame_mse(base.at(s_ref).only(op)) for op in base.base}
    total = sum(mses.values())
    shares = {op: (m / total if total > 0 else 0.0) for op, m in mses.items()}
    config: dict[str, Any] = ({"kind": "blur2d", "quantiles": res.quantiles} if isinstance(base, Blur2d) else
                              {"kind": "strength", "family": family, "ops": base.base, "quantiles": res.quantiles})
    # goodness of fit on held-out scenes (in-sample when there is only one scene); the floor on every real pair
    ev = held if held is not None else calib
    synth_stats, sheet, synth_held = [], [], []
    secs: dict[str, float] = {"perturb": 0.0, "render": 0.0}
    for i, p in enumerate(ev.pairs):
        s = draw_strength(config, p.seed)
        synth = ev.bench.corrupted(base.at(s), i, seconds=secs)
        synth_held.append(synth)
        synth_stats.append(stats.pair_stats(synth, ev.bench.clean[i], lpips=lpips))
        if i < 3:
            mid = len(p.clean) // 2
            sheet.append((p.clean[mid], p.corrupted[mid], synth[mid]))
    groups = [p.scene for p in ev.pairs]
    every = [calib, *([held] if held is not None else [])]
    gof = goodness.compare(ev.stats, synth_stats, groups, groups, stats.STAT_NAMES,
                           floor_stats=[st for side in every for st in side.stats],
                           floor_groups=[p.scene for side in every for p in side.pairs])
    gof["held_out"] = held is not None
    gof["scenes"] = sorted(set(groups))
    realism = None
    if opts.realism_steps > 0:
        realism = _realism(base, config, calib, held, synth_held, floor, opts, label=label, regime=regime, say=say)
    result = {"family": label, "base_family": family, "regime": regime, "search": res.to_dict(), "op_shares": shares,
              "op_shares_strength": s_ref, "config": config, "goodness": gof, "realism": realism, "mix_search": mix_info,
              "calibration_scenes": sorted({p.scene for p in pairs})}
    plot = {"real_psnr": real_psnr.tolist(),
            "synth_psnr": np.concatenate([st["frame_psnr"] for st in synth_stats]).tolist(),
            "real_held_psnr": np.concatenate([st["frame_psnr"] for st in ev.stats]).tolist(),
            "real_spectrum": np.nanmean(goodness.stat_matrix(ev.stats, stats.SPECTRUM_NAMES), axis=0).tolist(),
            "synth_spectrum": np.nanmean(goodness.stat_matrix(synth_stats, stats.SPECTRUM_NAMES), axis=0).tolist(),
            "sheet": sheet}
    n = max(len(ev.pairs), 1)
    cost = {"family": label, "regime": regime, "pairs": len(ev.pairs), "perturb": round(secs["perturb"] / n, 4),
            "render": round(secs["render"] / n, 4),
            "seconds_per_pair": round((secs["perturb"] + secs["render"]) / n, 4)}
    return result, plot, cost


def _realism(base: Strength | Blur2d, config: Mapping[str, Any], calib: _Side, held: _Side | None,
             synth_held: Sequence[np.ndarray], floor: dict[str, Any] | None, opts: Options, *, label: str,
             regime: str, say: Callable[[str], None]) -> dict[str, Any]:
    """The CNN two-sample test of one family (`morphgs.calibration.realism`): trained on the
    calibration scenes' real pairs and their synthetic counterparts (strengths drawn from the
    calibrated distribution with each pair's seed, as curate draws them), scored on the held-out
    scenes' (cross-fitted when there are none). "indistinguishable": its interval's lower end at or
    below the floor interval's upper end."""
    t0 = time.perf_counter()

    def synth_clips(side: _Side, frames: Sequence[np.ndarray] | None = None) -> list[Clip]:
        out = []
        for i, p in enumerate(side.pairs):
            rgb = frames[i] if frames is not None else side.bench.corrupted(base.at(draw_strength(config, p.seed)), i)
            out.append(Clip(rgb, side.bench.clean[i], p.scene, 1))
        return out

    if held is not None:
        test = classifier_test(calib.clips() + synth_clips(calib), held.clips() + synth_clips(held, synth_held),
                               seed=opts.seed, steps=opts.realism_steps, repeats=opts.repeats)
    else:
        test = classifier_test(calib.clips() + synth_clips(calib, synth_held), seed=opts.seed,
                               steps=opts.realism_steps, repeats=opts.repeats)
    lo, hi = test["ci"][0], (floor or {}).get("ci", [float("nan")] * 2)[1]
    same = bool(math.isfinite(lo) and math.isfinite(hi) and lo <= hi)
    say(f"calibrate: {label} vs {regime}: classifier AUC {test['auc']:.3f} [{test['ci'][0]:.3f}, {test['ci'][1]:.3f}]"
        + (f", floor {floor['auc']:.3f}" if floor else "") + f" [{time.perf_counter() - t0:.1f} s]")
    return {"classifier": test, "floor": floor, "indistinguishable": same}
