"""`morphgs export-difix DIR OUT.json`: Difix3D's data.json for a curated folder."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("export-difix", help="write Difix3D's data.json (train/test) for a curated folder")
    p.add_argument("dataset", metavar="DIR", help="curate output folder")
    p.add_argument("out", metavar="OUT.json", help="the data.json to write")
    p.add_argument("--prompt", default="remove degradation", help="prompt of every entry")
    p.add_argument("--relative", action="store_true", help="paths relative to OUT.json's folder")
    p.add_argument("--config", action="append", dest="configs", help="only these config names")
    p.add_argument("--ref-offset", type=int, default=None, help="frames to the reference view (half a clip)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from morphgs.curation import export_difix

    counts = export_difix(args.dataset, args.out, prompt=args.prompt, relative=args.relative,
                          configs=args.configs, ref_offset=args.ref_offset)
    print(f"{args.out}: {counts['train']} train and {counts['test']} test entries")
    return 0
