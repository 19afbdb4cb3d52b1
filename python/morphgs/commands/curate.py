"""`morphgs curate SCENE... --out DIR`: clean/corrupted training pairs (docs/curation.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from morphgs.reliability import add_wait_argument


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 832x480, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return w, h


def _rgb(text: str) -> tuple[float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"background must be R,G,B in [0,1], got {text!r}") from None
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"background must be R,G,B in [0,1], got {text!r}")
    return vals  # type: ignore[return-value]


_CONFIG_FORMS = """\
config forms (--config CFG):
  spatial | radiometric | morphological | naive
                      the paper's presets at its default strengths
  NAME@SCALE          a preset with every intensity times SCALE, pruning min(SCALE*p, 1)
                      (PerturbConfig.scaled; morphological@2 prunes everything)
  NAME~STRENGTH       a family at STRENGTH of the smooth, scene-aware strength
                      parameterisation (keep = 0.5^s, log-space scale noise, rotation angle;
                      docs/perturbation.md), e.g. morphological~1.5
  blur2d | blur2d@SIGMA
                      the 2D baseline: clean frames blurred by SIGMA pixels (--blur-sigma)
  sparse:K | sparse:K@STEPS
                      a real 3DGS reconstruction from every K-th recorded view (cached in DIR/fits)
  sparse-n:N | sparse-n:N@STEPS
                      a reconstruction from N views spread evenly
  underfit:F | underfit:F@STEPS
                      a reconstruction from all views stopped at the fraction F (0 < F < 1) of
                      its schedule of STEPS (default 3000); the fractions of a scene share one run
  cross:P | cross:P@STEPS
                      a reconstruction from the first fraction P of the capture path, the pairs
                      rendered along the rest of it
  FILE.json           a PerturbConfig dict, {"kind": "blur2d", "sigma" | "quantiles"}, {"kind":
                      "sparse", "every" | "n", "steps", "fit"}, {"kind": "underfit" | "cross",
                      "fraction", "steps", "fit"} or {"kind": "strength", "family",
                      "strength" | "quantiles", "ops"} (what morphgs calibrate writes: each pair
                      draws its strength or sigma, recorded in the manifest)
"""


def register(sub: Any) -> None:
    p = sub.add_parser(
        "curate", help="render clean/corrupted training pairs from scenes into a dataset folder",
        description="Render K clean/corrupted pairs per scene and config into DIR (resumable). "
                    "With no SCENE, the built-in synthetic sample scenes are used.",
        epilog=_CONFIG_FORMS, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", nargs="*", metavar="SCENE",
                   help="scene file, or folder with a scene file and optional transforms.json/COLMAP")
    p.add_argument("--out", required=True, help="dataset folder (a rerun resumes in it)")
    p.add_argument("--config", action="append", dest="configs", metavar="CFG",
                   help="corruption (forms below); repeat for several (default: morphological)")
    p.add_argument("--pairs-per-scene", "-k", type=int, default=2, help="pairs per scene and config (2)")
    p.add_argument("--frames", "-f", type=int, default=49, help="frames per pair (49; the paper uses 16 and 49)")
    p.add_argument("--size", type=_size, default=(832, 480), help="WxH (832x480)")
    p.add_argument("--seed", type=int, default=0, help="run seed (0)")
    p.add_argument("--test-fraction", type=float, default=0.1, help="share of scenes in the test split (0.1)")
    p.add_argument("--split-seed", type=int, default=0, help="seed of the train/test split (0)")
    p.add_argument("--blur-sigma", type=float, default=2.0, help="blur2d sigma in pixels (2.0)")
    p.add_argument("--depth", action="store_true", help="also write depth as EXR")
    p.add_argument("--video", action="store_true", help="write MP4s (imageio-ffmpeg) instead of PNG frames")
    p.add_argument("--fps", type=int, default=16, help="video frame rate (16)")
    p.add_argument("--background", type=_rgb, default=(0.0, 0.0, 0.0), help="R,G,B in [0,1] (0,0,0)")
    p.add_argument("--trajectory", choices=("auto", "cameras", "orbit", "photos"), default="auto",
                   help="recorded cameras when present (auto), only them, an orbit, or runs of the capture's "
                        "own photos, which are then the clean side (photos)")
    p.add_argument("--stride", type=int, default=None,
                   help="clip stride along recorded cameras or photos (= frames)")
    p.add_argument("--orbit-arc", type=float, default=60.0, help="degrees an orbit pair sweeps (60)")
    p.add_argument("--fov", type=float, default=50.0, help="vertical field of view of orbits, degrees (50)")
    p.add_argument("--up", default="file", metavar="UP",
                   help="world up of orbits around scene files without cameras: file (the loaders' "
                        "convention, -y), scene (from the Gaussians), +x..-z or X,Y,Z (file); the "
                        "built-in sample scenes keep +z")
    p.add_argument("--chunk", type=int, default=8, help="frames per render pass (8)")
    p.add_argument("--workers", "-j", type=int, default=1, help="local worker processes (1)")
    p.add_argument("--backend", choices=("local", "ray"), default="local", help="local processes or Ray")
    p.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--shard-index", type=int, default=0, help="this job's shard (0)")
    p.add_argument("--num-shards", type=int, default=1, help="number of shards (1)")
    p.add_argument("--sample-gaussians", type=int, default=100_000,
                   help="Gaussians per built-in sample scene when no SCENE is given (100000)")
    p.add_argument("--dry-run", action="store_true", help="show the plan and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_wait_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from morphgs.curation import curate

    try:
        summary = curate(
            args.scenes, args.out, configs=args.configs or ["morphological"],
            pairs_per_scene=args.pairs_per_scene, frames=args.frames, resolution=args.size, seed=args.seed,
            test_fraction=args.test_fraction, split_seed=args.split_seed, blur_sigma=args.blur_sigma,
            depth=args.depth, video=args.video, fps=args.fps, background=args.background,
            trajectory=args.trajectory, stride=args.stride, orbit_arc_degrees=args.orbit_arc,
            fov_y_degrees=args.fov, up=args.up, chunk=args.chunk, workers=args.workers, backend=args.backend,
            ray_address=args.ray_address, shard_index=args.shard_index, num_shards=args.num_shards,
            builtin_gaussians=args.sample_gaussians, dry_run=args.dry_run, progress=not args.no_progress,
            wait=args.wait)
    except ValueError as e:  # bad settings: a usage error, not a crash
        print(f"morphgs curate: error: {e}", file=sys.stderr)
        return 2
    if not args.dry_run:
        print(summary.text(), file=sys.stderr)
    return 0 if summary.ok else 1
