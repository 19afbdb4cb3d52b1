"""SIGTERM handled like Ctrl-C.

Clusters (SLURM, Kubernetes) and Ray send SIGTERM some seconds before they kill a job. Python's
default is to die at once, losing the step in progress and anything not yet written. Two ways
to handle it:

- `sigterm_raises()`: SIGTERM raises `Preempted` (a KeyboardInterrupt) in the main thread, so
  the code's Ctrl-C path runs: `morphgs fit` writes its checkpoint (the native loop checks for
  signals at every step), `morphgs curate` abandons the pair in progress (its temporary folder
  is removed by the next run) and keeps every finished one. `morphgs.cli.main` installs it for
  every command and prints the command's resume line.
- `StopRequest()`: SIGTERM and a first Ctrl-C only set a flag that a loop checks between steps
  (`morphgs train` finishes the step, writes a checkpoint and returns); a second Ctrl-C raises
  KeyboardInterrupt at once.

`signals_held()` holds both for a few writes that must land together (`morphgs fit`'s batch of
loss rows) and delivers them when the block ends.

Both restore the previous handlers on exit and do nothing outside the main thread.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

__all__ = ["Preempted", "StopRequest", "sigterm_raises", "signals_held"]


class Preempted(KeyboardInterrupt):
    """SIGTERM arrived (raised like Ctrl-C's KeyboardInterrupt)."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_preempted(signum: int, frame: FrameType | None) -> None:
    raise Preempted(signum)


@contextmanager
def signals_held() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM wait: each one that arrives is delivered again, to the
    handler of before, when the block ends (so Ctrl-C raises there). For a few writes that must
    land together (a batch of CSV rows that a checkpoint counts on). Nothing outside the main
    thread, nor for a signal that is ignored."""
    if not _main_thread():
        yield
        return
    caught: list[int] = []
    old: dict[int, Any] = {}
    try:
        for s in (signal.SIGINT, signal.SIGTERM):
            h = signal.getsignal(s)
            if h is not None and h != signal.SIG_IGN:
                old[s] = signal.signal(s, lambda signum, frame: caught.append(signum))
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        for n in dict.fromkeys(caught):
            signal.raise_signal(n)


@contextmanager
def sigterm_raises() -> Iterator[None]:
    """Within the block, SIGTERM raises `Preempted` in the main thread."""
    if not _main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _raise_preempted)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


class StopRequest:
    """A flag set by SIGTERM or a first Ctrl-C while the `with` block runs.

    `requested` is the signal's name ("SIGTERM", "SIGINT") or None; a loop checks it between
    steps, stops cleanly (checkpoint) and says how to resume. A second Ctrl-C raises
    KeyboardInterrupt at once.
    """

    def __init__(self) -> None:
        self.requested: str | None = None
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        if signum == signal.SIGINT and self.requested == "SIGINT":
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name

    def __enter__(self) -> StopRequest:
        if _main_thread():
            for s in (signal.SIGTERM, signal.SIGINT):
                self._old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old.clear()
