"""Warnings as the command line shows them: one line `morphgs CMD: warning: ...`, whatever the
warning's category and whichever process raised it.

`morphgs.cli.main` installs the format for the command it runs and names the command in the
environment (`ENV`); `import morphgs` installs it again in every process the command starts
(spawned workers of `curate`, `fit` and `ablate`, Ray workers), which inherit that variable.
A MorphgsWarning shows its message; any other warning (NumPy's RuntimeWarning, a library's
UserWarning) its category first, and no Python file, line or source. MORPHGS_TRACEBACK=1 keeps
Python's own format, for bug reports.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from typing import Any

ENV = "MORPHGS_CLI_COMMAND"


def one_line_format(command: str) -> Callable[..., str]:
    """A `warnings.formatwarning` that writes `morphgs COMMAND: warning: ...` on one line."""

    def fmt(message: Any, category: type[Warning], filename: str, lineno: int, line: str | None = None) -> str:
        from morphgs._core import MorphgsWarning

        text = " | ".join(ln.strip() for ln in str(message).splitlines() if ln.strip())
        if not issubclass(category, MorphgsWarning):
            text = f"{category.__name__}: {text}" if text else category.__name__
        return f"morphgs {command}: warning: {text}\n"

    return fmt


def install(command: str) -> Callable[[], None]:
    """Show warnings as `command`'s one-line warnings here and in the processes started from now
    on; returns the function that puts back what was there."""
    old_format, old_env = warnings.formatwarning, os.environ.get(ENV)
    os.environ[ENV] = command
    if not os.environ.get("MORPHGS_TRACEBACK"):
        warnings.formatwarning = one_line_format(command)

    def restore() -> None:
        warnings.formatwarning = old_format
        if old_env is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = old_env

    return restore


def install_from_environment() -> None:
    """In a process a command started (`ENV` set): its one-line format (`import morphgs` calls
    this)."""
    command = os.environ.get(ENV)
    if command and not os.environ.get("MORPHGS_TRACEBACK"):
        warnings.formatwarning = one_line_format(command)
