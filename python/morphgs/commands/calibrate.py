"""`morphgs calibrate [SCENE...] --regime sparse:20 --family morphological --out CALIB [--real DIR]`
(docs/calibration.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from morphgs.commands.curate import _size
from morphgs.reliability import add_wait_argument


def _grid(text: str) -> list[float]:
    from morphgs.calibration.search import log_grid

    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid must look like 0.0625,128, got {text!r}") from None
    if not (0 < lo < hi < 1e6):
        raise argparse.ArgumentTypeError(f"grid needs 0 < LO < HI, got {text!r}")
    return log_grid(lo, hi)


def register(sub: Any) -> None:
    p = sub.add_parser(
        "calibrate", help="match perturbation strength to real (e.g. sparse-view) artifacts",
        description="Make real pairs (a sparse-view regime: fits cached, resumable) or read them (--real), then "
                    "search each family's strength so its pairs match them: a strength distribution per "
                    "(family, regime), written as a config file `morphgs curate --config FILE` accepts, with "
                    "calibration.json and report.md. With no SCENE, the built-in sample scenes are used.")
    p.add_argument("scenes", nargs="*", metavar="SCENE", help="clean scenes, as for morphgs curate")
    p.add_argument("--out", required=True, help="output folder (a rerun reuses its real pairs and sparse fits)")
    p.add_argument("--regime", action="append", dest="regimes", default=[], metavar="REGIME",
                   help="real-fit regime: sparse:K, sparse-n:N, underfit:F or cross:P, optionally @STEPS (fit "
                        "length); repeatable")
    p.add_argument("--family", action="append", dest="families", default=[], metavar="FAMILY",
                   help="spatial, radiometric, morphological or naive (ops in the preset's proportions), "
                        "blur2d (the 2D render blur, strength = sigma in pixels), or a JSON file {\"family\": ..., "
                        "\"ops\": {op: base value}} fixing the ops, or all (every family and blur2d); repeatable (default: "
                        "morphological). With several, report.md and the last lines rank them by how closely their "
                        "pairs resemble the real ones")
    p.add_argument("--search-mix", action="store_true",
                   help="also search each family's op mix (a simplex grid of the ops' weights, each mix matched to "
                        "the real PSNR) and keep the mix whose SSIM, coverage, spectrum, colour shift and temporal "
                        "error are closest to the real pairs' on the calibration scenes")
    p.add_argument("--objective", choices=("psnr", "realism"), default="psnr",
                   help="psnr: match the real pairs' PSNR (the op mix fixed, or --search-mix's); realism: also "
                        "search the op mix of families of two or more ops (Optuna TPE, seeded, resumable from "
                        "OUT/realism/) for the pairs a CNN classifier can least tell from the real ones (psnr)")
    p.add_argument("--trials", type=int, default=16,
                   help="candidates of --objective realism's search, per family and regime (16)")
    p.add_argument("--realism-steps", type=int, default=240,
                   help="training steps of the CNN two-sample test reported for every family on the held-out "
                        "scenes (0 skips it); the realism search trains half as many per candidate (240)")
    p.add_argument("--realism-repeats", type=int, default=1,
                   help="networks per fold of every classifier (the reported test, its floor and the realism "
                        "search's), their logits averaged: steadier AUCs at N times the classifier's cost (1)")
    p.add_argument("--mix-steps", type=int, default=3,
                   help="resolution of --search-mix's grid: weights in multiples of 1/N (3)")
    p.add_argument("--real", default=None, metavar="DIR",
                   help="a curated folder of real pairs (any pairs whose corrupted side is real); each config "
                        "name in it is a regime")
    p.add_argument("--pairs-per-scene", "-k", type=int, default=2, help="real pairs per scene and regime (2)")
    p.add_argument("--frames", "-f", type=int, default=16, help="frames per pair (16)")
    p.add_argument("--size", type=_size, default=(128, 96), help="WxH of the regimes' pairs (128x96)")
    p.add_argument("--seed", type=int, default=0, help="run seed (0)")
    p.add_argument("--sample-gaussians", type=int, default=100_000,
                   help="Gaussians per built-in sample scene when no SCENE is given (100000)")
    p.add_argument("--sample-scenes", type=int, default=4,
                   help="built-in sample scenes when no SCENE is given (4: two calibrate, two are held out)")
    p.add_argument("--sample-fit-steps", type=int, default=1500,
                   help="fit length on the built-in scenes for a --regime without @STEPS (1500)")
    p.add_argument("--grid", type=_grid, default=None, metavar="LO,HI",
                   help="strength range of the log-grid scan, two points per octave (0.0625,128)")
    p.add_argument("--lpips", action="store_true", help="also compare LPIPS (needs the installed weights)")
    p.add_argument("--workers", "-j", type=int, default=1, help="curate workers for the regimes' pairs (1)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    add_wait_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from morphgs.calibration.pairs import CalibrationError
    from morphgs.calibration.run import calibrate

    try:
        doc = calibrate(args.scenes, args.out, regimes=args.regimes, families=args.families or ["morphological"],
                        real=args.real, pairs_per_scene=args.pairs_per_scene, frames=args.frames,
                        resolution=args.size, seed=args.seed, builtin_gaussians=args.sample_gaussians,
                        lpips=args.lpips, **({"grid": args.grid} if args.grid else {}), workers=args.workers,
                        plots=not args.no_plots, wait=args.wait, builtin_scenes=args.sample_scenes,
                        builtin_fit_steps=args.sample_fit_steps, search_mix=args.search_mix,
                        mix_steps=args.mix_steps, objective=args.objective, trials=args.trials,
                        realism_steps=args.realism_steps, realism_repeats=args.realism_repeats)
    except (CalibrationError, ValueError) as e:
        print(f"morphgs calibrate: error: {e}", file=sys.stderr)
        return 2
    for r in doc["results"]:
        s = r["search"]
        state = "reachable" if s["reachable"] else "UNREACHABLE"
        print(f"{r['family']} / {r['regime']}: {state}, real median {s['target_median_psnr']:.2f} dB, "
              f"median strength {s['median_strength'] if s['median_strength'] is not None else 'n/a'}, "
              f"{'matched' if r['goodness']['matched'] else 'not matched'} -> {args.out}/{r['config_file']}")
    for regime, entries in doc["ranking"].items():
        if len(entries) > 1:
            top = entries[0]
            sep = f", d' {_num(top['separation'])}" if top.get("separation") is not None else ""
            print(f"closest to the real {regime} pairs: {top['family']} (AUC {_num(top['auc'])}{sep}; furthest off "
                  f"{top['furthest']}, {_num(top['furthest_excess'])} IQR beyond its floor); then "
                  + ", ".join(x["family"] for x in entries[1:]))
    return 0


def _num(v: object) -> str:
    return f"{v:.2f}" if isinstance(v, (int, float)) and v == v else "n/a"
