"""`morphgs calibrate`: the pipeline from scenes (and a sparse-view regime, or a folder of real
pairs) to calibrated strength distributions, config files, calibration.json and report.md."""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.calibration import goodness, stats
from morphgs.calibration.mix import mix_distances, mixed, simplex_grid
from morphgs.calibration.pairs import Bench, CalibrationError, RealPair, read_real_pairs
from morphgs.calibration.search import DEFAULT_GRID, search
from morphgs.strength import FAMILIES, Blur2d, Strength, draw_strength

__all__ = ["BUILTIN_FIT_STEPS", "BUILTIN_SCENES", "MIN_TRAIN_VIEWS", "calibrate"]

#: A regime must leave at least this many training views per scene.
MIN_TRAIN_VIEWS = 2
#: Built-in scenes used when no SCENE is given: two calibrate, two are held out.
BUILTIN_SCENES = 4
#: The sparse fits' length on the built-in scenes when a regime gives no @STEPS: four fits of
#: 1500 steps cost what two of curate's default 3000 did (docs/calibration.md, "Measured").
BUILTIN_FIT_STEPS = 1500


def _cpu_seconds() -> float:
    """CPU time of this process and its finished children (curate's worker processes)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "-" for c in text)


def _check_regime(spec: str, sources: Sequence[Any], resolution: tuple[int, int],
                  default_steps: int | None = None) -> Any:
    """Parse a --regime (sparse:K / sparse-n:N[@STEPS]) and check it leaves enough views;
    `default_steps` is the fit length when the regime gives none."""
    from morphgs.curation.plan import ConfigSpec, parse_config
    from morphgs.curation.sparse import CAPTURE_VIEWS, split_views

    try:
        cfg = parse_config(spec)
    except ValueError as e:
        raise CalibrationError(f"--regime {spec}: {e}") from None
    if cfg.kind != "sparse":
        raise CalibrationError(f"--regime {spec}: expected sparse:K or sparse-n:N (optionally @STEPS); "
                               "use --real DIR for other real pairs")
    if default_steps is not None and "steps" not in cfg.params:
        cfg = ConfigSpec(f"{cfg.label}-{default_steps}steps", "sparse", {**cfg.params, "steps": default_steps})
    for src in sources:
        recorded = src.load_cameras(resolution) if src.cameras is not None else None
        n = len(recorded) if recorded is not None else CAPTURE_VIEWS
        train, _ = split_views(n, cfg.params)
        if len(train) < MIN_TRAIN_VIEWS:
            raise CalibrationError(f"--regime {spec}: leaves {len(train)} training view(s) of {n} for scene "
                                   f"{src.id} ({src.describe()}); at least {MIN_TRAIN_VIEWS} are needed "
                                   "(use a smaller K or a larger N)")
    return cfg


def _split_scenes(pairs: Sequence[RealPair]) -> tuple[list[RealPair], list[RealPair]]:
    """(calibration pairs, held-out pairs): scenes in sorted order alternate; with one scene the
    same pairs serve both (the goodness of fit is then in-sample, and says so)."""
    scenes = sorted({p.scene for p in pairs})
    if len(scenes) < 2:
        return list(pairs), []
    held = set(scenes[1::2])
    return [p for p in pairs if p.scene not in held], [p for p in pairs if p.scene in held]


def _pair_stats(corrupted: np.ndarray, clean: np.ndarray, lpips: bool) -> dict[str, Any]:
    return stats.pair_stats(corrupted, clean, lpips=lpips)


def _family(spec: str) -> tuple[str, Strength | Blur2d]:
    """A --family: a family name (its ops at the preset's proportions), blur2d (strength = sigma
    in pixels) or a JSON file {"family", "ops"} fixing the ops and their proportions; (label, base
    config at strength 1)."""
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


#: What `--family all` stands for: every strength family and the 2D blur.
ALL_FAMILIES: tuple[str, ...] = (*FAMILIES, Blur2d.family)


def expand_families(families: Sequence[str]) -> list[str]:
    """`families` with "all" replaced by `ALL_FAMILIES` (those not already named), order kept."""
    out: list[str] = []
    for f in families:
        for g in (ALL_FAMILIES if f == "all" else (f,)):
            if g not in out or f != "all":
                out.append(g)
    return out


def rank_families(results: Sequence[Mapping[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per regime, the families ordered from the most to the least like the real pairs on the
    held-out scenes: matched ones first, then by the classifier's AUC (0.5 = indistinguishable),
    then by how far the furthest statistic lies beyond its real-vs-real floor, then by name (so
    the order is the same on every run). Each entry: family, auc, furthest, furthest_excess,
    matched."""
    by_regime: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        g = r["goodness"]
        auc = g["classifier"]["auc"]
        by_regime.setdefault(r["regime"], []).append({
            "family": r["family"], "auc": auc, "furthest": g["furthest"],
            "furthest_excess": g["furthest_excess"], "matched": bool(g["matched"])})

    def finite(v: Any) -> tuple[bool, float]:  # missing or NaN values sort last
        ok = isinstance(v, (int, float)) and math.isfinite(v)
        return (not ok, float(v) if ok else 0.0)

    def key(e: dict[str, Any]) -> tuple[Any, ...]:
        return (not e["matched"], *finite(e["auc"]), *finite(e["furthest_excess"]), e["family"])

    return {k: sorted(v, key=key) for k, v in by_regime.items()}


def _search_mix(label: str, base: Strength, pairs: list[RealPair], bench: Bench, real_psnr: np.ndarray,
                pair_of_frame: np.ndarray, *, steps: int, grid: Sequence[float], lpips: bool,
                say: Callable[[str], None]) -> tuple[Strength, dict[str, Any]]:
    """The op-mix search (morphgs.calibration.mix) on the calibration pairs: each candidate mix
    matched pair by pair to the real PSNR (a scan at one point per octave of `grid`, then
    interpolation), its pairs compared with the real ones on the other statistics; the mix of
    lowest score among those that reach the real median wins. Returns (chosen config, report)."""
    t0 = time.perf_counter()
    coarse = list(grid)[::2] if len(grid) >= 6 else list(grid)
    real_stats = [_pair_stats(p.corrupted, p.clean, lpips) for p in pairs]
    rows: list[dict[str, Any]] = []
    synth_all = []
    for w in simplex_grid(list(base.base), steps):
        cfg = mixed(base, w)

        def measure(s: float, c: Strength = cfg) -> np.ndarray:
            return bench.frame_psnr(c.at(s))

        res = search(measure, real_psnr, grid=coarse, pairs=pair_of_frame, iters=6, tol_db=0.1)
        synth = [_pair_stats(bench.corrupted(cfg.at(s), k), bench.clean[k], lpips)
                 for k, s in enumerate(res.pair_strengths)]
        synth_all.append(synth)
        rows.append({"weights": w, "ops": cfg.base, "reachable": res.reachable,
                     "median_strength": res.median_strength, "median_psnr_reached": res.median_psnr_reached,
                     "pair_strengths": res.pair_strengths})
    for row, d in zip(rows, mix_distances(real_stats, synth_all)):
        row.update(d)
    pool = [i for i, r in enumerate(rows) if r["reachable"]] or list(range(len(rows)))
    best = min(pool, key=lambda i: (rows[i]["score"] if np.isfinite(rows[i]["score"]) else np.inf, i))
    chosen: dict[str, float] = rows[best]["weights"]
    say(f"calibrate: {label}: op mix {', '.join(f'{k} {v:.2f}' for k, v in chosen.items())} chosen of {len(rows)} "
        f"(score {rows[best]['score']:.3f}; the preset's {rows[0]['score']:.3f}) [{time.perf_counter() - t0:.1f} s]")
    info = {"steps": steps, "grid": coarse, "candidates": rows, "chosen": best, "preset": 0,
            "scenes": sorted({p.scene for p in pairs})}
    return mixed(base, chosen), info


def _calibrate_one(label: str, base: Strength | Blur2d, regime: str, pairs: list[RealPair], bench: Bench,
                   held_bench: Bench | None,
                   held: list[RealPair], *, grid: Sequence[float], lpips: bool, say: Callable[[str], None],
                   search_mix: bool = False, mix_steps: int = 3) -> dict[str, Any]:
    family = base.family
    real_psnr = np.concatenate([stats.frame_psnr(p.corrupted, p.clean) for p in pairs])
    pair_of_frame = np.concatenate([np.full(len(p.clean), k) for k, p in enumerate(pairs)])
    mix_info = None
    if search_mix and isinstance(base, Strength) and len(base.base) >= 2:
        base, mix_info = _search_mix(label, base, pairs, bench, real_psnr, pair_of_frame, steps=mix_steps, grid=grid,
                                     lpips=lpips, say=say)
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
    # goodness of fit on held-out scenes (in-sample when there is only one scene)
    eval_pairs, eval_bench = (held, held_bench) if held_bench is not None else (pairs, bench)
    real_stats, synth_stats, sheet = [], [], []
    for i, p in enumerate(eval_pairs):
        real_stats.append(_pair_stats(p.corrupted, p.clean, lpips))
        s = draw_strength(config, p.seed)
        synth = eval_bench.corrupted(base.at(s), i)
        synth_stats.append(_pair_stats(synth, eval_bench.clean[i], lpips))
        if i < 3:
            mid = len(p.clean) // 2
            sheet.append((p.clean[mid], p.corrupted[mid], synth[mid]))
    groups = [p.scene for p in eval_pairs]
    every = list(pairs) + list(held) if held_bench is not None else list(pairs)
    every_stats = [_pair_stats(p.corrupted, p.clean, lpips) for p in every[:len(every) - len(held)]] + (
        real_stats if held_bench is not None else [])
    gof = goodness.compare(real_stats, synth_stats, groups, groups, stats.STAT_NAMES, floor_stats=every_stats,
                           floor_groups=[p.scene for p in every])
    gof["held_out"] = held_bench is not None
    gof["scenes"] = sorted(set(groups))
    return {"family": label, "base_family": family, "regime": regime, "search": res.to_dict(), "op_shares": shares,
            "op_shares_strength": s_ref, "config": config, "goodness": gof, "mix_search": mix_info,
            "calibration_scenes": sorted({p.scene for p in pairs}),
            "_plot": {"real_psnr": real_psnr.tolist(),
                      "synth_psnr": np.concatenate([st["frame_psnr"] for st in synth_stats]).tolist(),
                      "real_held_psnr": np.concatenate([st["frame_psnr"] for st in real_stats]).tolist(),
                      "real_spectrum": np.nanmean(goodness.stat_matrix(real_stats, _SPEC), axis=0).tolist(),
                      "synth_spectrum": np.nanmean(goodness.stat_matrix(synth_stats, _SPEC), axis=0).tolist(),
                      "sheet": sheet}}


_SPEC = tuple(n for n in stats.STAT_NAMES if n.startswith("spectrum_"))


def calibrate(
    scenes: Iterable[str | os.PathLike[str]] = (),
    out: str | os.PathLike[str] = "out/calib",
    *,
    regimes: Sequence[str] = (),
    families: Sequence[str] = ("morphological",),
    real: str | os.PathLike[str] | None = None,
    pairs_per_scene: int = 2,
    frames: int = 16,
    resolution: tuple[int, int] = (128, 96),
    seed: int = 0,
    builtin_gaussians: int = 100_000,
    grid: Sequence[float] = DEFAULT_GRID,
    lpips: bool = False,
    workers: int = 1,
    plots: bool = True,
    log: Callable[[str], None] | None = None,
    wait: bool = False,
    builtin_scenes: int = BUILTIN_SCENES,
    builtin_fit_steps: int | None = BUILTIN_FIT_STEPS,
    search_mix: bool = False,
    mix_steps: int = 3,
) -> dict[str, Any]:
    """Calibrate each family's strength distribution to each regime's real pairs (docs/calibration.md).

    Args:
        scenes: clean scenes (files or folders, as `morphgs curate`); none = the built-in samples.
        out: output folder: calibration.json, configs/<family>-<regime>.json, report.md, plots,
            and real/ (the regimes' real pairs and their cached sparse fits; a rerun reuses them).
        regimes: sparse-view regimes (`sparse:K`, `sparse-n:N`, optionally `@STEPS`).
        families: strength families (spatial, radiometric, morphological, naive; their ops keep the
            preset's proportions), or JSON files {"family", "ops"} fixing the ops' base values.
        real: a curated folder of real pairs instead of (or besides) regimes; each config name in
            it is a regime.
        pairs_per_scene, frames, resolution, seed: the real pairs the regimes make.
        builtin_gaussians: Gaussians per built-in scene. grid: the strength scan's log grid.
        lpips: also compute LPIPS (where the weights are installed). workers: curate's workers
            for the regimes' pairs. plots: write the PNG plots. log: message sink (stderr).
        wait: when another process writes `out`, wait for it instead of raising FolderBusyError
            (`out` is locked while calibrate runs; the curate of its real pairs locks out/real).
        builtin_scenes: built-in scenes when `scenes` is empty (4: two calibrate, two held out).
        builtin_fit_steps: the sparse fits' length on the built-in scenes for a regime without
            @STEPS (1500; None: curate's default).
        search_mix: also search each family's op mix (morphgs.calibration.mix; families of two or
            more ops) and calibrate the mix whose pairs resemble the real ones most.
        mix_steps: the mix grid's resolution (weights in multiples of 1/mix_steps).

    Returns:
        The calibration.json content.

    Raises:
        CalibrationError: an unknown family, a bad or too sparse regime, no real pairs, pairs of
            mismatched sizes, a real pair's scene not among the scenes.
        morphgs.reliability.FolderBusyError: another process writes `out` (names its pid, host
            and start time).
    """
    from morphgs.reliability import folder_lock

    with folder_lock(out, command="calibrate", wait=wait, say=log):
        from morphgs.curation import curate
        from morphgs.curation.sources import builtin_sources, discover

        say = log or (lambda m: print(m, file=sys.stderr))
        t_wall, t_cpu = time.perf_counter(), _cpu_seconds()
        given_all = "all" in families
        families = expand_families(families)
        bases = [_family(f) for f in families]
        if len({lbl for lbl, _ in bases}) != len(bases):
            raise CalibrationError(f"--family: the families must have distinct names, got {[lbl for lbl, _ in bases]}"
                                   + (f" (--family all already names {', '.join(ALL_FAMILIES)})" if given_all else ""))
        if not families:
            raise CalibrationError("at least one --family is needed")
        if not regimes and real is None:
            raise CalibrationError("give at least one --regime (e.g. sparse:20) or --real DIR")
        if builtin_fit_steps is not None and builtin_fit_steps < 1:
            raise CalibrationError(f"--sample-fit-steps must be >= 1, got {builtin_fit_steps}")
        if mix_steps < 1:
            raise CalibrationError(f"--mix-steps must be >= 1, got {mix_steps}")
        scene_list = [str(s) for s in scenes]
        if scene_list:
            sources, problems = discover(scene_list)
            if problems:
                raise CalibrationError(f"scene {problems[0][0]}: {problems[0][1]}")
        else:
            if builtin_scenes < 1:
                raise CalibrationError(f"--sample-scenes must be >= 1, got {builtin_scenes}")
            sources = builtin_sources(builtin_scenes, n_gaussians=builtin_gaussians)
        out_dir = Path(out)
        groups: dict[str, list[RealPair]] = {}
        fit_steps: dict[str, int | None] = {}
        for spec in regimes:
            cfg = _check_regime(spec, sources, resolution, None if scene_list else builtin_fit_steps)
            fit_steps[spec] = cfg.params.get("steps")
            real_dir = out_dir / "real"
            summary = curate(scene_list, real_dir, configs=[cfg], pairs_per_scene=pairs_per_scene, frames=frames,
                             resolution=resolution, seed=seed, test_fraction=0.0, builtin_gaussians=builtin_gaussians,
                             builtin_scenes=builtin_scenes, workers=workers, progress=False, log=say)
            if not summary.ok:
                raise CalibrationError(f"--regime {spec}: making the real pairs failed: {summary.failed}")
            groups[spec] = read_real_pairs(real_dir, regimes=[cfg.label])
        if real is not None:
            for p in read_real_pairs(real):
                groups.setdefault(p.regime, []).append(p)
        sizes = {p.clean.shape[1:3] for ps in groups.values() for p in ps}
        if len(sizes) > 1:
            raise CalibrationError(f"real pairs of mismatched sizes {sorted(sizes)}: the regimes' pairs (--size) and "
                                   "--real's must have one size")
        needed = sorted({p.scene for ps in groups.values() for p in ps})
        by_id = {s.id: s for s in sources}
        missing = [n for n in needed if n not in by_id]
        if missing:
            raise CalibrationError(f"the real pairs' scene(s) {', '.join(missing)} are not among the scenes "
                                   f"({', '.join(sorted(by_id)) or 'none'}); give them as SCENE arguments")
        loaded = {n: by_id[n].load() for n in needed}
        results = []
        for regime, pairs in groups.items():
            calib, held = _split_scenes(pairs)
            bench = Bench(loaded, calib)
            held_bench = Bench(loaded, held) if held else None
            for label, base in bases:
                results.append(_calibrate_one(label, base, regime, calib, bench, held_bench, held, grid=grid,
                                              lpips=lpips, say=say, search_mix=search_mix, mix_steps=mix_steps))
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "configs").mkdir(exist_ok=True)
        for r in results:
            name = f"{r['family']}-{_slug(r['regime'])}.json"
            r["config_file"] = f"configs/{name}"
            (out_dir / "configs" / name).write_text(json.dumps(r["config"], indent=1) + "\n", encoding="utf-8")
        from morphgs import __version__

        doc = {"schema": 1, "morphgs_version": __version__, "scenes": [s.describe() for s in sources],
               "regimes": list(groups), "families": [lbl for lbl, _ in bases],
               "real": None if real is None else str(real),
               "pairs_per_scene": pairs_per_scene, "seed": seed, "fit_steps": fit_steps, "search_mix": search_mix,
               "frames": sorted({len(p.clean) for ps in groups.values() for p in ps}),
               "resolution": [int(v) for v in next(iter(sizes))[::-1]],
               "results": [{k: v for k, v in r.items() if k != "_plot"} for r in results]}
        doc["ranking"] = rank_families(results)
        from morphgs.calibration.report import write_report

        write_report(out_dir, doc, [r["_plot"] for r in results], plots=plots)
        (out_dir / "calibration.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        # timings apart, so that calibration.json, the configs and report.md are the same bytes on every run
        secs = {"wall": round(time.perf_counter() - t_wall, 2), "cpu": round(_cpu_seconds() - t_cpu, 2)}
        (out_dir / "timings.json").write_text(json.dumps(secs) + "\n", encoding="utf-8")
        say(f"calibrate: wrote {out_dir / 'calibration.json'}, {out_dir / 'report.md'} and "
            f"{len(results)} config(s) in {out_dir / 'configs'} ({secs['wall']:.1f} s, CPU {secs['cpu']:.1f} s)")
        return doc
