"""`morphgs convert IN OUT`: rewrite a scene in another format, chosen by OUT's extension."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import morphgs
from morphgs.saving import WRITERS, format_for


def register(sub: Any) -> None:
    p = sub.add_parser(
        "convert",
        help="convert a scene between formats (.ply, .compressed.ply, .splat, .spz, .glb; the "
        "input format is detected)",
        description="Read any supported scene (INRIA PLY, SuperSplat compressed PLY, .spz v1-v4, "
        "PlayCanvas SOG, glTF/GLB KHR_gaussian_splatting, SceneSplat .npy folders, .splat) and "
        "write it in the format named by OUT's extension: "
        + "; ".join(f"{k} = {v}" for k, v in WRITERS.items())
        + ".",
    )
    p.add_argument("input", help="the scene to read: a file or folder (format detected from its "
                   "content)")
    p.add_argument("output", help="the file to write: .ply, .compressed.ply, .splat, .spz or .glb")
    p.add_argument("--spz-version", type=int, choices=(3, 4), default=3,
                   help=".spz output version: 3 (gzip, default) or 4 (zstd streams)")
    p.set_defaults(func=run)


def convert(src: str | Path, dst: str | Path, *, spz_version: int = 3) -> morphgs.GaussianScene:
    """Load `src` and write it to `dst` in the format given by `dst`'s extension.

    Args:
        src: any scene file or folder `morphgs.load` reads.
        dst: the output path; its suffix (.ply, .compressed.ply, .splat, .spz or .glb, any
            case) picks the writer.
        spz_version: 3 or 4, for `.spz` output.

    Returns:
        The scene that was written.

    Raises:
        ValueError: `dst` has an unknown extension (checked before reading `src`).
        SceneFormatError: `src` is malformed or unsupported.
        OSError: a file cannot be read or written.
    """
    format_for(dst)
    scene = morphgs.load(src)
    morphgs.save(scene, dst, spz_version=spz_version)
    return scene


def run(args: argparse.Namespace) -> int:
    try:
        scene = convert(args.input, args.output, spz_version=args.spz_version)
    except ValueError as e:
        if isinstance(e, morphgs.MorphgsError):
            raise
        print(f"morphgs convert: error: {e}", file=sys.stderr)
        return 2
    print(f"{args.input} -> {args.output}: {len(scene):,} Gaussians, SH degree {scene.sh_degree}")
    return 0
