"""`morphgs fit DATA --out RUN`: fit a 3DGS scene to posed images on the CPU (docs/fit.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "fit", help="reconstruct a 3DGS scene from posed images (transforms.json or COLMAP) on the CPU",
        description="Optimise Gaussians to posed images with the 3DGS recipe (native, deterministic, "
                    "resumable: rerun the same command after a stop or a kill).")
    p.add_argument("data", nargs="*", help="transforms.json, or a dataset folder (transforms.json or COLMAP "
                                           "model + images); several (or a glob, or @LIST.txt): one run each "
                                           "under --out")
    p.add_argument("--out", help="run folder (a rerun resumes in it); with several captures the output root, "
                                 "one run folder per capture")
    p.add_argument("--workers", "-j", type=int, default=1,
                   help="captures fitted at once, in local worker processes (several captures only; 1)")
    p.add_argument("--config", help="TOML config file (partial files override the defaults)")
    p.add_argument("--preset", choices=("default", "mcmc", "sparse"), default=None,
                   help="start from a preset: default (gsplat/INRIA, 30k steps), mcmc, sparse (3000 steps, "
                        "MCMC capped at 300k)")
    p.add_argument("--strategy", choices=("default", "mcmc"), default=None, help="densification strategy")
    p.add_argument("--steps", type=int, default=None, help="training steps (config: 30000)")
    p.add_argument("--seed", type=int, default=None, help="seed (config: 0)")
    p.add_argument("--views", default="all",
                   help="training views: all, every:K (S_K), n:N (N spread evenly) or indices 0,8,16 (all)")
    p.add_argument("--holdout", default="every:8", help="held-out views: every:K, none or indices (every:8)")
    p.add_argument("--init", default="auto",
                   help="auto, points (COLMAP points3D / ply_file_path), random[:N], ply:PATH or scene:PATH (auto)")
    p.add_argument("--images", default=None, help="image folder instead of the dataset's (e.g. images_4)")
    p.add_argument("--downscale", type=int, default=1, help="shrink images and cameras by this factor (1)")
    p.add_argument("--restart", action="store_true", help="start over instead of resuming a run in --out")
    p.add_argument("--print-config", action="store_true", help="print the effective config as TOML and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--wait", action="store_true", help="if another process writes --out, wait for it")
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> Any:
    from morphgs.fit import FitConfig

    if args.config and args.preset:
        raise ValueError("give --config or --preset, not both")
    cfg = FitConfig.load(args.config) if args.config else FitConfig.preset(args.preset or "default")
    d = cfg.to_dict()
    for key in ("strategy", "steps", "seed"):
        v = getattr(args, key)
        if v is not None:
            d[key] = v
    return FitConfig.from_dict(d, source=args.config or "command line")


def run(args: argparse.Namespace) -> int:
    from morphgs.fit import fit

    try:
        cfg = _config(args)
    except ValueError as e:
        print(f"morphgs fit: error: {e}", file=sys.stderr)
        return 2
    if args.print_config:
        sys.stdout.write(cfg.to_toml())
        return 0
    if not args.data or not args.out:
        print("morphgs fit: error: DATA and --out are required", file=sys.stderr)
        return 2
    from morphgs.fit.many import expand_inputs, fit_many

    datas = expand_inputs(args.data)
    if len(datas) != 1 or len(args.data) != 1 or args.data[0] != datas[0]:
        try:
            many = fit_many(args.data, args.out, workers=args.workers, config=cfg, views=args.views,
                            holdout=args.holdout, init=args.init, images=args.images, downscale=args.downscale,
                            resume=not args.restart, wait=args.wait,
                            log=None if args.no_progress else (lambda m: print(f"morphgs fit: {m}", file=sys.stderr)))
        except KeyboardInterrupt:
            print(f"morphgs fit: interrupted; rerun the same command to resume in {args.out}", file=sys.stderr)
            return 130
        except ValueError as e:
            print(f"morphgs fit: error: {e}", file=sys.stderr)
            return 2
        print(many.text(), file=sys.stderr)
        return 1 if many.failed else 0
    try:
        res = fit(datas[0], args.out, config=cfg, views=args.views, holdout=args.holdout, init=args.init,
                  images=args.images, downscale=args.downscale, resume=not args.restart,
                  progress=not args.no_progress, wait=args.wait)
    except KeyboardInterrupt as e:
        from morphgs.reliability import Preempted

        why = "stopped by SIGTERM" if isinstance(e, Preempted) else "interrupted"
        print(f"morphgs fit: {why}; a checkpoint is in {args.out}: rerun the same command to resume",
              file=sys.stderr)
        return 143 if isinstance(e, Preempted) else 130
    lp = f" LPIPS {res.heldout_lpips:.4f}" if res.heldout_lpips is not None else ""
    held = (f", held-out PSNR {res.heldout_psnr:.3f} dB SSIM {res.heldout_ssim:.4f}{lp} on {len(res.heldout_views)} views"
            if res.heldout_psnr is not None else "")
    rate = f", {res.steps_per_second:.2f} steps/s" if res.steps_per_second else ""
    print(f"morphgs fit: {res.steps} steps, {res.gaussians} Gaussians{held}{rate} -> {res.ply}", file=sys.stderr)
    return 0
