"""`morphgs export FORMAT DIR OUT`: a curated folder in the layout a trainer reads (docs/exports.md)."""

from __future__ import annotations

import argparse
import sys
import warnings
from typing import Any

from morphgs.reliability import add_wait_argument

_FORMATS = ("diffsynth", "videox-fun", "thedenk", "webdataset", "difix")
_VIDEO = ("diffsynth", "videox-fun", "thedenk", "webdataset")
_CAPTIONED = ("diffsynth", "videox-fun", "thedenk")

# option dest -> the formats that take it (anything else given for another format is an error)
_ONLY = {
    "reference_frame": ("diffsynth",),
    "shard_size": ("webdataset",),
    "depth": ("webdataset",),
    "depth_dtype": ("webdataset",),
    "relative": ("difix",),
    "ref_offset": ("difix",),
    "captions": _CAPTIONED,
    "fps": _VIDEO,
    "crf": _VIDEO,
    "workers": _VIDEO,
}


def register(sub: Any) -> None:
    p = sub.add_parser(
        "export", help="write a curated folder in a trainer's layout (DiffSynth, VideoX-Fun, TheDenk, "
                       "WebDataset, Difix3D)",
        description="Write the pairs of a curated folder (morphgs curate) as the dataset a trainer reads, "
                    "keeping the train/test split. OUT is a new folder; an existing non-empty OUT is "
                    "replaced only with --overwrite.")
    p.add_argument("format", choices=_FORMATS, metavar="FORMAT", help=f"one of {', '.join(_FORMATS)}")
    p.add_argument("dataset", metavar="DIR", help="curate output folder")
    p.add_argument("out", metavar="OUT", help="export folder to create")
    p.add_argument("--overwrite", action="store_true", help="replace an existing export at OUT")
    p.add_argument("--config", action="append", dest="configs", metavar="NAME", help="only pairs of these configs")
    p.add_argument("--prompt", default=None, help="text of every pair (default: 'remove degradation')")
    p.add_argument("--captions", metavar="FILE.json",
                   help="per-pair or per-scene text: {\"pair id or scene\": \"text\"}")
    p.add_argument("--fps", type=float, default=None, help="frame rate of MP4s encoded from frames (16)")
    p.add_argument("--crf", type=int, default=None, help="H.264 quality, lower is better (18)")
    p.add_argument("--workers", type=int, default=None, help="clips encoded at once (the thread count)")
    p.add_argument("--reference-frame", type=int, default=None, metavar="N",
                   help="diffsynth: add a reference_image column, clean frame N of each pair")
    p.add_argument("--shard-size", default=None, metavar="SIZE",
                   help="webdataset: shard size with a unit, e.g. 512MB, 2GB or 100samples (512MB)")
    p.add_argument("--no-depth", dest="depth", action="store_const", const=False, default=None,
                   help="webdataset: leave out depth.npz even when the pairs have depth")
    p.add_argument("--depth-float16", dest="depth_dtype", action="store_const", const="float16", default=None,
                   help="webdataset: depth as float16 (4.4x smaller, relative error <= 2^-11) instead of float32")
    p.add_argument("--relative", action="store_true", default=None, help="difix: paths relative to OUT")
    p.add_argument("--ref-offset", type=int, default=None, help="difix: frames to the reference view (half a clip)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_wait_argument(p)
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> dict[str, Any]:
    from morphgs.exports import ExportError, load_captions, parse_shard_size

    for dest, formats in _ONLY.items():
        if getattr(args, dest) is not None and args.format not in formats:
            flag = {"depth": "--no-depth", "depth_dtype": "--depth-float16"}.get(dest, "--" + dest.replace("_", "-"))
            raise ExportError(f"{flag} applies to {', '.join(formats)}, not {args.format}")
    opts: dict[str, Any] = {"overwrite": args.overwrite, "configs": args.configs}
    if args.prompt is not None:
        opts["prompt"] = args.prompt
    opts["progress"] = not args.no_progress
    for dest in ("fps", "crf", "workers", "reference_frame", "depth", "depth_dtype", "relative", "ref_offset"):
        if getattr(args, dest) is not None:
            opts[dest] = getattr(args, dest)
    if args.captions is not None:
        opts["captions"] = load_captions(args.captions)
    if args.shard_size is not None:
        try:
            opts["shard_bytes"], opts["shard_samples"] = parse_shard_size(args.shard_size)
        except ValueError as e:
            raise ExportError(f"--shard-size: {e}") from None
    return opts


def run(args: argparse.Namespace) -> int:
    from morphgs import MorphgsWarning
    from morphgs.exports import export

    opts = _options(args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MorphgsWarning)
        try:
            summary = export(args.format, args.dataset, args.out, wait=args.wait, **opts)
        finally:
            for w in caught:
                if issubclass(w.category, MorphgsWarning):
                    print(f"morphgs export: warning: {w.message}", file=sys.stderr)
                else:
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    print(summary.text())
    return 0
