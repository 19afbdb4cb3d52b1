"""Write an export into a temporary folder beside OUT and rename it into place at the end, so a failed
or interrupted export leaves nothing half-made, and an existing export is replaced only on request."""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from morphgs.exports.source import ExportError
from morphgs.reliability import folder_lock

__all__ = ["check_out", "staged_dir"]


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def check_out(out: Path, source: Path, *, overwrite: bool) -> None:
    """Refuse an OUT that is the source (or holds it), a file, or a non-empty folder without `overwrite`.

    Raises:
        ExportError: naming OUT and what is wrong.
    """
    if _inside(source.resolve(), out.resolve()):
        raise ExportError(f"{out}: the export folder would hold (or be) the curated folder {source}")
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise ExportError(f"{out}: exists and is not a folder; give a folder path for the export")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ExportError(f"{out}: exists and is not empty; pass --overwrite (overwrite=True) to replace it")


@contextmanager
def staged_dir(out: str | os.PathLike[str], source: Path, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary folder beside `out`; on success it replaces `out`, on error it is removed.

    The previous contents of `out` (with `overwrite`) are moved aside first and removed only once the
    new export is in place, so a crash in between leaves the old export or the new one, never a mix.

    One export writes `out` at a time: the lock `.NAME.morphgs.lock` beside it (morphgs.reliability)
    is held from the check to the rename.

    Raises:
        ExportError: from `check_out`. FolderBusyError: another process exports into `out`.
    """
    final = Path(out).absolute()
    with folder_lock(final, command="export", beside=True):
        with _staged(final, source, overwrite=overwrite) as tmp:
            yield tmp


@contextmanager
def _staged(final: Path, source: Path, *, overwrite: bool) -> Iterator[Path]:
    check_out(final, source, overwrite=overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    tag = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp = final.with_name(f".{final.name}.tmp-{tag}")
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old-{tag}")
        os.rename(final, old)
    try:
        os.rename(tmp, final)
    except BaseException:
        if old is not None:
            os.rename(old, final)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
