"""Checksums of saved folders (checkpoints, cache entries): written at save time, verified
before use, so a file truncated by a crash during a copy, a full disk or a bad sync is found
before it is loaded (and another, intact one chosen).

`CHECKSUMS` (`checksums.json`) maps each file's path relative to the folder to its size and
sha256.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from morphgs._core import MorphgsError

__all__ = ["CHECKSUMS", "ChecksumError", "file_digest", "verify_checksums", "write_checksums"]

CHECKSUMS = "checksums.json"


class ChecksumError(MorphgsError):
    """A saved folder whose files do not match the checksums written with them."""


def file_digest(path: str | os.PathLike[str]) -> str:
    """sha256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_checksums(folder: str | os.PathLike[str]) -> Path:
    """Record size and sha256 of every file under `folder` (but the record itself) in
    `folder/checksums.json`, fsynced. Call it last, once every other file is written."""
    root = Path(folder)
    entries = {}
    for f in sorted(root.rglob("*")):
        if f.is_file() and f.name != CHECKSUMS:
            rel = f.relative_to(root).as_posix()
            entries[rel] = {"size": f.stat().st_size, "sha256": file_digest(f)}
    out = root / CHECKSUMS
    with open(out, "w", encoding="utf-8") as fh:
        fh.write(json.dumps({"version": 1, "files": entries}, indent=1, sort_keys=True) + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    return out


def verify_checksums(folder: str | os.PathLike[str], *, required: bool = False, sizes_only: bool = False
                     ) -> str | None:
    """None when every file listed in `folder/checksums.json` has its recorded size and sha256,
    else what is wrong (naming the file). A folder without the record passes unless `required`
    (folders written before checksums existed). `sizes_only` skips the hashes (a quick check
    that finds truncated and missing files, for large caches)."""
    root = Path(folder)
    rec_path = root / CHECKSUMS
    if not rec_path.is_file():
        return f"{rec_path} is missing" if required else None
    try:
        files = json.loads(rec_path.read_text(encoding="utf-8"))["files"]
        items = [(str(k), int(v["size"]), str(v["sha256"])) for k, v in files.items()]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        return f"{rec_path} is unreadable ({type(e).__name__}: {e})"
    for rel, size, digest in items:
        f = root / rel
        try:
            actual = f.stat().st_size
        except OSError:
            return f"{f} is missing"
        if actual != size:
            return f"{f} has {actual} bytes, {size} were written"
        if sizes_only:
            continue
        try:
            if file_digest(f) != digest:
                return f"{f} does not match its checksum"
        except OSError as e:
            return f"{f} is unreadable ({e.strerror or e})"
    return None
