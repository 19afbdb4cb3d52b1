"""The `morphgs` command line. Each subcommand lives in `morphgs.commands.<name>` and exposes
`register(subparsers)`, which adds its parser and sets `func(args) -> int` as the handler."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from morphgs import __version__
from morphgs._core import MorphgsError

# Order is the order shown in --help.
_COMMAND_MODULES = (
    "morphgs.commands.info",
    "morphgs.commands.curate",
    "morphgs.commands.export",
    "morphgs.commands.fit",
    "morphgs.commands.export_difix",
    "morphgs.commands.preview",
    "morphgs.commands.train",
    "morphgs.commands.refine",
    "morphgs.commands.convert",
    "morphgs.commands.sample",
    "morphgs.commands.perturb",
    "morphgs.commands.eval",
    "morphgs.commands.ablate",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="morphgs",
        description="3D-consistent corrupted/clean training pairs from Gaussian-splat scenes.",
    )
    parser.add_argument("--version", action="version", version=f"morphgs {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (MorphgsError, OSError) as e:
        print(f"morphgs {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"morphgs {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
