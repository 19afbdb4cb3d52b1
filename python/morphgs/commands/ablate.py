"""`morphgs ablate --study study.toml --out STUDY`: the paper's perturbation ablation (Table 1)
end to end, cached per stage and resumable (docs/ablation.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from morphgs.reliability import add_wait_argument, folder_lock


def register(sub: Any) -> None:
    p = sub.add_parser(
        "ablate", help="train one refiner per corruption and score them on sparse-view test scenes (Table 1)",
        description="Run an ablation study: captures, training sets, training (with CKA probes), sparse-view "
                    "test sets, refine, 2D and 3D metrics, and the report (table.md, results.csv/json, plots). "
                    "Every stage is cached under --out by a hash of what it reads; a rerun continues.")
    p.add_argument("--study", default=None, help="study TOML (keys it leaves out come from the preset)")
    p.add_argument("--preset", choices=("smoke", "toy", "paper", "real", "real-smoke"), default=None,
                   help="the base settings (default: the study file's `preset`, else toy)")
    p.add_argument("--out", default=None, help="the study folder (required unless --print-config)")
    p.add_argument("--print-config", action="store_true", help="print every setting, pinned, and exit")
    p.add_argument("--dry-run", action="store_true", help="show the plan, job counts and a cost estimate, and exit")
    p.add_argument("--workers", "-j", type=int, default=1, help="local worker processes per stage level (1)")
    p.add_argument("--backend", choices=("local", "ray"), default="local", help="local processes or Ray (as curate)")
    p.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--cluster", default=None, metavar="NODESxCPUS[xGPUS]",
                   help="with --dry-run --backend ray: the cluster to plan for (e.g. 8x32x8; default: this "
                        "machine): CPU- and GPU-hours, peak memory per job and the spread over the nodes")
    p.add_argument("--up", default=None,
                   help="world up of the capture orbits of scene files without cameras: file (the loaders' "
                        "-y, default), scene (from the Gaussians), +x..-z or X,Y,Z (write --up=-y); overrides "
                        "the study's capture.up")
    add_wait_argument(p)
    p.add_argument("--recompute", action="store_true",
                   help="accept a study folder made with other settings: recompute what depends on the changes")
    p.set_defaults(func=run)


def _plan_text(study: Any, out: Path, workers: int, backend: str = "local", cluster: str | None = None) -> str:
    from morphgs.ablation import cache
    from morphgs.ablation.estimate import estimate
    from morphgs.ablation.model_check import missing_model_folders
    from morphgs.ablation.recipe import build_plan
    from morphgs.ablation.scenes import resolve_scenes
    from morphgs.ablation.stages import STAGES

    sc = resolve_scenes(study)
    jobs = build_plan(study, out, sc)
    # torch jobs run single-threaded (two share the 2 cores); fits and renders already use both cores
    par = max(1, min(workers, 2))
    est = {k: v / (par if k in ("training", "refine", "metrics2d") else 1) for k, v in estimate(study, jobs).items()}
    lines = [f"study {study.source} (preset {study.preset}) -> {out}",
             f"scenes: {len(sc.train)} train, {len(sc.test)} test ({', '.join(sc.test[:6])}"
             f"{' ...' if len(sc.test) > 6 else ''})",
             f"conditions: {', '.join(c.label for c in study.conditions)}; regimes: {', '.join(r.label for r in study.regimes)}; "
             f"seeds: {study.seeds}; model: {study['model']['name']}",
             "stage        jobs   to do   estimate"]
    total = 0.0
    for st in STAGES:
        js = [j for j in jobs if j.ref.stage == st]
        if not js:  # calibration, without calibrated conditions
            continue
        todo = sum(not cache.is_done(j.ref) for j in js)
        s = est.get(st, 0.0)
        total += s
        gpu = " (GPU)" if st == "training" and study["model"]["name"] != "tiny" else ""
        lines.append(f"{st:<12} {len(js):>5} {todo:>7}   {_dur(s)}{gpu}")
    lines.append(f"total estimate: {_dur(total)} with -j {workers} (unit costs of a quiet 2-core Zen 5, scaled "
                 "in pixels, frames, steps and fitted Gaussians: an estimate, 2-3x short on a slower or shared CPU; "
                 "docs/ablation.md)")
    if backend == "ray":
        import os

        from morphgs.ablation.estimate import cluster_plan, parse_cluster

        shape = parse_cluster(cluster) if cluster else (1, os.cpu_count() or 1, 0)
        lines += cluster_plan(study, jobs, shape, max(1, shape[1] // max(1, workers)))
    for m in missing_model_folders(study):
        lines.append(f"note: a real run would stop here: {m}")
    return "\n".join(lines)


def _dur(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def run(args: argparse.Namespace) -> int:
    from morphgs.ablation import load_study, run_study, to_toml

    study = load_study(args.study, preset=args.preset, up=args.up)
    if args.print_config:
        sys.stdout.write(to_toml(study))
        return 0
    if not args.out:
        print("morphgs ablate: error: --out STUDY is required (the study folder)", file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.cluster and not (args.dry_run and args.backend == "ray"):
        print("morphgs ablate: error: --cluster plans a Ray cluster: use it with --dry-run --backend ray",
              file=sys.stderr)
        return 2
    if args.dry_run:
        if args.cluster:
            from morphgs.ablation.estimate import parse_cluster

            try:
                parse_cluster(args.cluster)
            except ValueError as e:
                print(f"morphgs ablate: error: {e}", file=sys.stderr)
                return 2
        print(_plan_text(study, out, args.workers, args.backend, args.cluster))
        return 0
    with folder_lock(out, command="ablate", wait=args.wait):
        ledger = run_study(study, out, workers=args.workers, recompute=args.recompute, backend=args.backend,
                           ray_address=args.ray_address)
    counts = ledger.counts()
    done = sum(c["computed"] for c in counts.values())
    reused = sum(c["reused"] for c in counts.values())
    print(f"morphgs ablate: {done} stage output(s) computed, {reused} reused -> {out / 'table.md'}", file=sys.stderr)
    return 0
