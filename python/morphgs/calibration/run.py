"""`morphgs calibrate`: the command around `pipeline.calibrate_pairs`: under a lock on its output
folder, it checks the options, finds the scenes, makes each sparse-view regime's real pairs with
curate (or reads a folder of them), loads the scenes, calibrates, and writes the outputs
(`outputs.write_outputs`) and timings.json."""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from morphgs.calibration.outputs import document, write_outputs
from morphgs.calibration.pairs import CalibrationError, RealPair, by_regime, read_real_pairs
from morphgs.calibration.pipeline import ALL_FAMILIES, calibrate_pairs, expand_families, parse_family
from morphgs.calibration.objective import OBJECTIVES, TRIALS
from morphgs.calibration.realism import STEPS
from morphgs.calibration.search import DEFAULT_GRID

__all__ = ["BUILTIN_FIT_STEPS", "BUILTIN_SCENES", "MIN_TRAIN_VIEWS", "calibrate", "find_scenes", "load_scenes"]

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


def _check_regime(spec: str, sources: Sequence[Any], resolution: tuple[int, int],
                  default_steps: int | None = None) -> Any:
    """Parse a --regime (a real-fit config: sparse:K, sparse-n:N, underfit:F or cross:P, each
    [@STEPS]) and check it leaves enough views; `default_steps` is the fit length when the
    regime gives none."""
    from morphgs.curation.plan import FIT_KINDS, ConfigSpec, parse_config
    from morphgs.curation.sparse import CAPTURE_VIEWS, split_views

    try:
        cfg = parse_config(spec)
    except ValueError as e:
        raise CalibrationError(f"--regime {spec}: {e}") from None
    if cfg.kind not in FIT_KINDS:
        raise CalibrationError(f"--regime {spec}: expected sparse:K, sparse-n:N, underfit:F or cross:P (optionally "
                               "@STEPS); use --real DIR for other real pairs")
    if default_steps is not None and "steps" not in cfg.params:
        cfg = ConfigSpec(f"{cfg.label}-{default_steps}steps", cfg.kind, {**cfg.params, "steps": default_steps})
    for src in sources:
        recorded = src.load_cameras(resolution) if src.cameras is not None else None
        n = len(recorded) if recorded is not None else CAPTURE_VIEWS
        train, _ = split_views(n, cfg.params, cfg.kind)
        if len(train) < MIN_TRAIN_VIEWS:
            raise CalibrationError(f"--regime {spec}: leaves {len(train)} training view(s) of {n} for scene "
                                   f"{src.id} ({src.describe()}); at least {MIN_TRAIN_VIEWS} are needed "
                                   "(use a smaller K, a larger N or a larger P)")
        if cfg.kind == "cross" and n - len(train) < 2:
            raise CalibrationError(f"--regime {spec}: leaves {n - len(train)} of {n} views of scene {src.id} to render "
                                   "the pairs along (at least 2 are needed; use a smaller P)")
    return cfg


def _curate_order(specs: Sequence[str], cfgs: Sequence[Any]) -> list[int]:
    """The order the regimes' pairs are made in: as given, but underfit regimes by ascending
    step, so that regimes sharing an underfit run advance it instead of fitting a branch."""
    from morphgs.curation.plan import fit_steps, stop_step

    def key(i: int) -> tuple[int, int, int]:
        c = cfgs[i]
        if c.kind != "underfit":
            return (0, 0, i)
        return (1, stop_step(c.params["fraction"], fit_steps(c.params)), i)

    return sorted(range(len(specs)), key=key)


def _costs(real_dir: Path, labels: Mapping[str, str], real: str | os.PathLike[str] | None,
           calibration: Any) -> dict[str, Any]:
    """costs.json: the cost per pair of each regime's real pairs (from their manifest records,
    `morphgs.curation.costs`) and of each family at its calibrated strength (measured on the
    goodness-of-fit pairs)."""
    from morphgs.curation import costs, load_manifest

    regimes: dict[str, Any] = {}
    if labels:
        recs = load_manifest(real_dir).values()
        for spec, label in labels.items():
            regimes[spec] = {"config": label, **costs.summarise([r for r in recs if r.get("config_name") == label])}
    if real is not None:
        recs = load_manifest(Path(real)).values()
        for name in sorted({str(r.get("config_name", "real")) for r in recs}):
            regimes.setdefault(name, {"config": name, **costs.summarise(
                [r for r in recs if str(r.get("config_name", "real")) == name])})
    return {"regimes": regimes, "families": list(calibration.costs)}


def _costs_md(doc: Mapping[str, Any]) -> str:
    def f(v: Any) -> str:
        return "n/a" if v is None else f"{v:.3f}"

    lines = ["# Cost per pair", "",
             "Wall seconds of this run's machine (docs/calibration.md, \"Cost per pair\"): for a real regime, the "
             "corrupted side of each pair (loading its fit and half the render pass) plus its share of the fit; for a "
             "family, perturbing the clean scene at the calibrated strength and rendering it (the goodness-of-fit "
             "pairs).",
             "", "| real regime | pairs | fits | fit seconds (all) | corrupted side s/pair | **cost s/pair** |",
             "|---|---|---|---|---|---|"]
    for spec, c in doc["regimes"].items():
        lines.append(f"| {spec} | {c['pairs']} | {c['fits']} | {f(c['fit_seconds'])} | {f(c['corrupted_seconds'])} | "
                     f"**{f(c['seconds_per_pair'])}** |")
    lines += ["", "| family | vs regime | pairs | perturb s/pair | render s/pair | **cost s/pair** |",
              "|---|---|---|---|---|---|"]
    for c in doc["families"]:
        lines.append(f"| {c['family']} | {c['regime']} | {c['pairs']} | {f(c['perturb'])} | {f(c['render'])} | "
                     f"**{f(c['seconds_per_pair'])}** |")
    return "\n".join(lines) + "\n"


def _fmt_cost(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"


def find_scenes(scenes: Sequence[str], *, builtin_scenes: int = BUILTIN_SCENES,
                builtin_gaussians: int = 100_000) -> list[Any]:
    """The clean scenes' sources (`morphgs.curation.sources.SceneSource`), found as `morphgs curate`
    finds them; none given: `builtin_scenes` built-in sample scenes of `builtin_gaussians` each.

    Raises:
        CalibrationError: a scene that cannot be found or read (the first one), builtin_scenes < 1.
    """
    from morphgs.curation.sources import builtin_sources, discover

    if scenes:
        sources, problems = discover(list(scenes))
        if problems:
            raise CalibrationError(f"scene {problems[0][0]}: {problems[0][1]}")
        return sources
    if builtin_scenes < 1:
        raise CalibrationError(f"--sample-scenes must be >= 1, got {builtin_scenes}")
    return builtin_sources(builtin_scenes, n_gaussians=builtin_gaussians)


def load_scenes(sources: Sequence[Any], groups: Mapping[str, Sequence[RealPair]]) -> dict[str, Any]:
    """Scene id -> clean GaussianScene, for the scenes of the pairs in `groups` (only those loaded).

    Raises:
        CalibrationError: a pair's scene not among `sources` (naming the scenes and SCENE).
    """
    needed = sorted({p.scene for ps in groups.values() for p in ps})
    by_id = {s.id: s for s in sources}
    missing = [n for n in needed if n not in by_id]
    if missing:
        raise CalibrationError(f"the real pairs' scene(s) {', '.join(missing)} are not among the scenes "
                               f"({', '.join(sorted(by_id)) or 'none'}); give them as SCENE arguments")
    return {n: by_id[n].load() for n in needed}


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
    objective: str = "psnr",
    trials: int = TRIALS,
    realism_steps: int = STEPS,
    realism_repeats: int = 1,
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
        objective: "psnr" or "realism" (the op mix searched for the pairs the CNN classifier can
            least tell from the real ones; `morphgs.calibration.objective`; its state files in
            out/realism/, so a rerun resumes). trials: the realism search's candidates.
        realism_steps: the CNN two-sample test's training steps (0: not run; the search trains
            half as many per candidate).
        realism_repeats: networks per fold of every classifier, logits averaged (steadier AUCs
            at that many times the classifier's cost).

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

        say = log or (lambda m: print(m, file=sys.stderr))
        t_wall, t_cpu = time.perf_counter(), _cpu_seconds()
        given_all = "all" in families
        families = expand_families(families)
        bases = [parse_family(f) for f in families]
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
        if objective not in OBJECTIVES:
            raise CalibrationError(f"--objective {objective}: unknown; valid objectives: {', '.join(OBJECTIVES)}")
        if trials < 1:
            raise CalibrationError(f"--trials must be >= 1, got {trials}")
        if realism_steps < 0:
            raise CalibrationError(f"--realism-steps must be >= 0, got {realism_steps}")
        if realism_repeats < 1:
            raise CalibrationError(f"--realism-repeats must be >= 1, got {realism_repeats}")
        if objective == "realism" and realism_steps == 0:
            raise CalibrationError("--objective realism needs the classifier: --realism-steps must be >= 1")
        if objective == "realism":
            from morphgs.strength import Strength

            mixable = [lbl for lbl, b in bases if isinstance(b, Strength) and len(b.base) >= 2]
            if not mixable:
                raise CalibrationError(f"--objective realism: no --family has two or more ops to mix "
                                       f"({', '.join(lbl for lbl, _ in bases)}); give a family such as sparse-like, "
                                       "naive or a JSON file {\"family\", \"ops\"} with several ops")
            for lbl, _ in bases:
                if lbl not in mixable:
                    say(f"calibrate: {lbl}: one op, nothing to mix; its strength is calibrated as with --objective psnr")
        scene_list = [str(s) for s in scenes]
        sources = find_scenes(scene_list, builtin_scenes=builtin_scenes, builtin_gaussians=builtin_gaussians)
        out_dir = Path(out)
        groups: dict[str, list[RealPair]] = {}
        fit_steps: dict[str, int | None] = {}
        real_dir = out_dir / "real"
        cfgs = [_check_regime(spec, sources, resolution, None if scene_list else builtin_fit_steps)
                for spec in regimes]
        for i in _curate_order(regimes, cfgs):
            spec, cfg = regimes[i], cfgs[i]
            summary = curate(scene_list, real_dir, configs=[cfg], pairs_per_scene=pairs_per_scene, frames=frames,
                             resolution=resolution, seed=seed, test_fraction=0.0, builtin_gaussians=builtin_gaussians,
                             builtin_scenes=builtin_scenes, workers=workers, progress=False, log=say)
            if not summary.ok:
                raise CalibrationError(f"--regime {spec}: making the real pairs failed: {summary.failed}")
        for spec, cfg in zip(regimes, cfgs):
            fit_steps[spec] = cfg.params.get("steps")
            groups[spec] = read_real_pairs(real_dir, regimes=[cfg.label])
        if real is not None:
            for regime, ps in by_regime(read_real_pairs(real)).items():
                groups.setdefault(regime, []).extend(ps)
        sizes = {p.clean.shape[1:3] for ps in groups.values() for p in ps}
        if len(sizes) > 1:
            raise CalibrationError(f"real pairs of mismatched sizes {sorted(sizes)}: the regimes' pairs (--size) and "
                                   "--real's must have one size")
        calibration = calibrate_pairs(groups, load_scenes(sources, groups), bases, grid=grid, lpips=lpips,
                                      search_mix=search_mix, mix_steps=mix_steps, objective=objective,
                                      trials=trials, realism_steps=realism_steps,
                                      search_steps=max(realism_steps // 2, 1), repeats=realism_repeats, seed=seed,
                                      state_dir=out_dir / "realism", say=say)
        doc = document(calibration, scenes=[s.describe() for s in sources], real=None if real is None else str(real),
                       pairs_per_scene=pairs_per_scene, seed=seed, fit_steps=fit_steps)
        write_outputs(out_dir, doc, calibration.plots, plots=plots)
        # timings and costs apart, so that calibration.json, the configs and report.md are the same
        # bytes on every run
        cost = _costs(real_dir, {spec: cfg.label for spec, cfg in zip(regimes, cfgs)}, real, calibration)
        (out_dir / "costs.json").write_text(json.dumps(cost, indent=1) + "\n", encoding="utf-8")
        (out_dir / "costs.md").write_text(_costs_md(cost), encoding="utf-8")
        secs = {"wall": round(time.perf_counter() - t_wall, 2), "cpu": round(_cpu_seconds() - t_cpu, 2)}
        (out_dir / "timings.json").write_text(json.dumps(secs) + "\n", encoding="utf-8")
        many = len(groups) > 1
        say("calibrate: cost per pair (s): " + "; ".join(
            [f"{k} {_fmt_cost(c['seconds_per_pair'])}" for k, c in cost["regimes"].items()]
            + [f"{c['family']}{' vs ' + c['regime'] if many else ''} {_fmt_cost(c['seconds_per_pair'])}"
               for c in cost["families"]]) + f" ({out_dir / 'costs.md'})")
        say(f"calibrate: wrote {out_dir / 'calibration.json'}, {out_dir / 'report.md'} and "
            f"{len(calibration.results)} config(s) in {out_dir / 'configs'} ({secs['wall']:.1f} s, "
            f"CPU {secs['cpu']:.1f} s)")
        return doc
