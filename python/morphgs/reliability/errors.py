"""The one line a CLI user sees for an exception."""

from __future__ import annotations

import re

__all__ = ["one_line", "unwrap_worker_message"]

# torch's DataLoader re-raises a worker's exception as the same type with this message:
# "Caught ExcName in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n ...
#  module.ExcName: the message\n"
_WORKER = re.compile(r"^Caught (\w+) in DataLoader worker process \d+\.\s*\nOriginal Traceback", re.S)


def unwrap_worker_message(text: str) -> str:
    """The original message behind a DataLoader worker's wrapped traceback (else `text`)."""
    m = _WORKER.match(text)
    if m is None:
        return text
    name = m.group(1)
    lines = text.rstrip("\n").splitlines()
    # the last line that starts the exception's own text ("pkg.mod.Name: msg" or "Name: msg")
    for i in range(len(lines) - 1, 0, -1):
        head = re.match(rf"^(?:[\w.]+\.)?{re.escape(name)}(?::\s?(.*))?$", lines[i])
        if head is not None:
            return "\n".join([head.group(1) or "", *lines[i + 1:]]).strip() or name
    return lines[-1].strip()


def one_line(exc: BaseException) -> str:
    """`exc` as one line: the DataLoader wrapper removed; an OSError as "FILE: reason"; the
    exception's type in front where the message alone would not say what failed."""
    if isinstance(exc, OSError) and exc.strerror:
        where = [str(f) for f in (exc.filename, exc.filename2) if f is not None]
        text = f"{' -> '.join(where)}: {exc.strerror}" if where else exc.strerror
    else:
        text = unwrap_worker_message(str(exc))
    if not _ours(exc) and not isinstance(exc, (OSError, ValueError)):
        text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return " | ".join(ln.strip() for ln in text.splitlines() if ln.strip()) or type(exc).__name__


def _ours(exc: BaseException) -> bool:
    from morphgs._core import MorphgsError

    return isinstance(exc, MorphgsError)
