"""`morphgs preview DIR`: contact sheet and animation of a few pairs."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("preview", help="contact sheet (PNG) and animation (GIF/MP4) of a curated folder")
    p.add_argument("dataset", metavar="DIR", help="curate output folder")
    p.add_argument("--out", default=None, help="output folder (DIR/preview)")
    p.add_argument("--pairs", type=int, default=4, help="pairs to show (4)")
    p.add_argument("--columns", type=int, default=6, help="frames per sheet row (6)")
    p.add_argument("--width", type=int, default=208, help="thumbnail width (208)")
    p.add_argument("--mp4", action="store_true", help="MP4 instead of GIF")
    p.add_argument("--fps", type=int, default=8, help="animation frame rate (8)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from morphgs.curation import preview

    sheet, anim = preview(args.dataset, out=args.out, pairs=args.pairs, columns=args.columns,
                          thumb_width=args.width, animation="mp4" if args.mp4 else "gif", fps=args.fps)
    print(f"wrote {sheet} and {anim}")
    return 0
