"""`manifest.jsonl`: one JSON line per finished pair, appended last (after the pair's folder is in
place) with flush + fsync, so a line always means a complete pair on disk.

A run with --num-shards > 1 appends to `manifest-shard{i}-of{n}.jsonl` instead (no two
processes append to one file); readers merge every `manifest*.jsonl` in the folder. A line cut
short by a killed process is ignored (the pair is simply redone).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["append", "expected_files", "is_complete", "load", "manifest_name"]

SCHEMA_VERSION = 1


def manifest_name(shard_index: int = 0, num_shards: int = 1) -> str:
    """The manifest file this process appends to."""
    if num_shards == 1:
        return "manifest.jsonl"
    return f"manifest-shard{shard_index:03d}-of{num_shards:03d}.jsonl"


def _lines(path: Path) -> Iterator[dict[str, Any]]:
    with open(path, encoding="utf-8") as f:
        for line in f:
            if not line.endswith("\n"):
                return  # cut short by a kill: not a finished pair
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict) and "pair_id" in rec:
                yield rec


def load(out_dir: str | os.PathLike[str]) -> dict[str, dict[str, Any]]:
    """All finished pairs of a dataset folder, keyed by pair_id (a later line wins)."""
    d = Path(out_dir)
    out: dict[str, dict[str, Any]] = {}
    if not d.is_dir():
        return out
    for path in sorted(d.glob("manifest*.jsonl")):
        for rec in _lines(path):
            out[rec["pair_id"]] = rec
    return out


def append(path: str | os.PathLike[str], record: dict[str, Any]) -> None:
    """Append one record as a single write, then flush and fsync."""
    line = json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n"
    with open(path, "a", encoding="utf-8") as f:
        f.write(line)
        f.flush()
        os.fsync(f.fileno())


def expected_files(record: dict[str, Any]) -> list[str]:
    """Paths (relative to the dataset folder) a finished pair must have."""
    paths = record["paths"]
    files = [paths["cameras"]]
    n = int(record["frames"])
    for side in ("clean", "corrupted"):
        if record.get("video"):
            files.append(paths[side])
        else:
            files += [f"{paths[side]}/{i:05d}.png" for i in range(n)]
        if record.get("depth"):
            files += [f"{paths[side + '_depth']}/{i:05d}.depth.exr" for i in range(n)]
    return files


def is_complete(out_dir: str | os.PathLike[str], record: dict[str, Any]) -> bool:
    """Whether every file of a manifest record exists (and is not empty)."""
    d = Path(out_dir)
    try:
        return all((d / f).stat().st_size > 0 for f in expected_files(record))
    except (OSError, KeyError, TypeError, ValueError):
        return False
