"""The `morphgs` command line. Each subcommand lives in `morphgs.commands.<name>` and exposes
`register(subparsers)`, which adds its parser and sets `func(args) -> int` as the handler."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from morphgs import __version__
from morphgs._cli_warnings import install as _install_warnings

# Order is the order shown in --help.
_COMMAND_MODULES = (
    "morphgs.commands.info",
    "morphgs.commands.curate",
    "morphgs.commands.calibrate",
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


# what a command that was stopped (Ctrl-C, SIGTERM) tells its user to do next
_RESUME = {
    "curate": "the finished pairs are kept; rerun the same command to resume",
    "calibrate": "the real pairs and sparse fits made so far are kept; rerun the same command to resume",
    "fit": "rerun the same command to resume from the last checkpoint",
    "train": "rerun with --resume to continue from the last checkpoint",
    "ablate": "finished stages are kept; rerun the same command to continue",
    "export": "nothing was left at OUT (the partial export is removed); rerun to export",
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Every warning is one `morphgs CMD: warning: ...` line (`_cli_warnings`);
    every failure ends in one `morphgs CMD: error: ...` line on stderr and a non-zero status
    (MORPHGS_TRACEBACK=1 shows the traceback instead, for bug reports); Ctrl-C and SIGTERM end
    with a line saying how to resume (exit 130 and 143)."""
    from morphgs.reliability import Preempted, one_line, sigterm_raises

    parser = build_parser()
    args = parser.parse_args(argv)
    cmd = args.command
    hint = _RESUME.get(cmd, "rerun the command")
    restore_warnings = _install_warnings(cmd)  # every warning one line, in worker processes too
    try:
        with sigterm_raises():
            return int(args.func(args) or 0)
    except Preempted:
        print(f"morphgs {cmd}: stopped by SIGTERM; {hint}", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"morphgs {cmd}: interrupted; {hint}", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - the CLI's one place where every failure becomes one line
        if os.environ.get("MORPHGS_TRACEBACK"):
            raise
        print(f"morphgs {cmd}: error: {one_line(e)}", file=sys.stderr)
        return 1
    finally:
        restore_warnings()


if __name__ == "__main__":
    sys.exit(main())
