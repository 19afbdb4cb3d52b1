"""`morphgs convert IN OUT`: rewrite a scene in another format, chosen by OUT's extension."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import morphgs

#: Output extensions and what writes them.
WRITERS = {
    ".ply": "INRIA 3DGS PLY (float32, all SH bands)",
    ".splat": "antimatter15 .splat (32 bytes per Gaussian, no SH bands)",
    ".spz": "Niantic .spz v3 (gzip, RUB axes)",
}


def register(sub: Any) -> None:
    p = sub.add_parser(
        "convert",
        help="convert a scene between formats (.ply, .splat, .spz; the input format is detected)",
        description="Read any supported scene (INRIA PLY, SuperSplat compressed PLY, .spz v2-v4, "
        ".splat) and write it in the format named by OUT's extension: "
        + "; ".join(f"{k} = {v}" for k, v in WRITERS.items())
        + ".",
    )
    p.add_argument("input", help="the scene to read (format detected from its content)")
    p.add_argument("output", help="the file to write: .ply, .splat or .spz")
    p.set_defaults(func=run)


def convert(src: str | Path, dst: str | Path) -> morphgs.GaussianScene:
    """Load `src` and write it to `dst` in the format given by `dst`'s extension.

    Args:
        src: any scene file `morphgs.load` reads.
        dst: the output path; its suffix (.ply, .splat or .spz, any case) picks the writer.

    Returns:
        The scene that was written.

    Raises:
        ValueError: `dst` has an unknown extension (checked before reading `src`).
        SceneFormatError: `src` is malformed or unsupported.
        OSError: a file cannot be read or written.
    """
    suffix = Path(dst).suffix.lower()
    if suffix not in WRITERS:
        raise ValueError(
            f"{dst}: unknown output extension {suffix!r}; expected one of "
            + ", ".join(sorted(WRITERS))
        )
    scene = morphgs.load(src)
    if suffix == ".ply":
        morphgs.save_ply(scene, dst)
    elif suffix == ".splat":
        morphgs.save_splat(scene, dst)
    else:
        morphgs.save_spz(scene, dst)
    return scene


def run(args: argparse.Namespace) -> int:
    try:
        scene = convert(args.input, args.output)
    except ValueError as e:
        if isinstance(e, morphgs.MorphgsError):
            raise
        print(f"morphgs convert: error: {e}", file=sys.stderr)
        return 2
    print(f"{args.input} -> {args.output}: {len(scene):,} Gaussians, SH degree {scene.sh_degree}")
    return 0
