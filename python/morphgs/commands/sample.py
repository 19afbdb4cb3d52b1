"""`morphgs sample OUT.ply --gaussians N`: write the built-in synthetic scene."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import morphgs
from morphgs import synthetic


def _count(text: str) -> int:
    """Parse a Gaussian count: digits with optional _ or , separators, or a k/M suffix."""
    t = text.strip().replace("_", "").replace(",", "")
    mult = 1
    if t[-1:] in ("k", "K"):
        t, mult = t[:-1], 1_000
    elif t[-1:] in ("m", "M"):
        t, mult = t[:-1], 1_000_000
    try:
        value = float(t) * mult if "." in t else int(t) * mult
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a Gaussian count: {text!r}") from None
    if value < 0 or value != int(value):
        raise argparse.ArgumentTypeError(f"not a Gaussian count: {text!r}")
    return int(value)


def register(sub: Any) -> None:
    p = sub.add_parser(
        "sample",
        help="write the built-in synthetic scene (a textured room corner with objects) as a PLY",
    )
    p.add_argument("out", type=Path, help="output .ply path")
    p.add_argument("--gaussians", "-n", type=_count, default=100_000,
                   help="number of Gaussians, e.g. 200000, 200k or 3M (default 100k)")
    p.add_argument("--sh-degree", type=int, choices=range(5), default=3, metavar="{0..4}",
                   help="SH degree of the colours (default 3)")
    p.add_argument("--seed", type=int, default=0, help="generator seed (default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    scene = synthetic.scene(args.gaussians, sh_degree=args.sh_degree, seed=args.seed)
    t1 = time.perf_counter()
    morphgs.save_ply(scene, args.out)
    t2 = time.perf_counter()
    size = args.out.stat().st_size
    print(f"wrote {args.out}: {len(scene):,} Gaussians, SH degree {scene.sh_degree}, "
          f"seed {args.seed}, {size / 1e6:.1f} MB (generated in {t1 - t0:.2f} s, "
          f"saved in {t2 - t1:.2f} s)")
    return 0
