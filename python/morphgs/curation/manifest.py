"""`manifest.jsonl`: one JSON line per finished pair, appended last (after the pair's folder is in
place) with flush + fsync, so a line always means a complete pair on disk.

A run with --num-shards > 1 appends to `manifest-shard{i}-of{n}.jsonl` instead (no two
processes append to one file); readers merge every `manifest*.jsonl` in the folder. A line cut
short by a killed process is ignored (the pair is simply redone).

One record per pair id: a run rewrites its own manifest file without duplicates and without
the records of pairs it redoes (`compact`) before appending, and never appends a pair twice.
A reader that still meets a pair id twice (two writers that ignored the folder lock, files
merged by hand) keeps the last line and warns once, naming the files.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsWarning

__all__ = ["append", "compact", "expected_files", "is_complete", "load", "manifest_name"]

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


def load(out_dir: str | os.PathLike[str], *, warn: bool = True) -> dict[str, dict[str, Any]]:
    """All finished pairs of a dataset folder, keyed by pair_id. A pair id listed more than once
    keeps its last line, with one MorphgsWarning naming how many and where (unless not `warn`)."""
    d = Path(out_dir)
    out: dict[str, dict[str, Any]] = {}
    if not d.is_dir():
        return out
    seen_in: dict[str, list[str]] = {}
    for path in sorted(d.glob("manifest*.jsonl")):
        for rec in _lines(path):
            out[rec["pair_id"]] = rec
            seen_in.setdefault(rec["pair_id"], []).append(path.name)
    dups = sorted(pid for pid, files in seen_in.items() if len(files) > 1)
    if dups and warn:
        files = sorted({f for pid in dups for f in seen_in[pid]})
        warnings.warn(f"{d}: {len(dups)} pair id(s) are listed more than once in {', '.join(files)} "
                      f"(first: {dups[0]}, {len(seen_in[dups[0]])} times); each is read once, from its last line "
                      "(a morphgs curate rerun on the folder rewrites the manifest)", MorphgsWarning, stacklevel=2)
    return out


def compact(path: str | os.PathLike[str], drop: Iterable[str] = ()) -> int:
    """Rewrite one manifest file with one line per pair id (its last) and without the pair ids in
    `drop` (pairs about to be redone), atomically. Returns the lines removed (0: left as it was)."""
    p = Path(path)
    if not p.is_file():
        return 0
    drop = set(drop)
    with open(p, encoding="utf-8") as f:
        raw = f.read().splitlines(keepends=True)
    last: dict[str, str] = {}
    for line in raw:
        if not line.endswith("\n"):
            break
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and "pair_id" in rec:
            last.pop(rec["pair_id"], None)  # keep the order of last appearance
            last[rec["pair_id"]] = line
    kept = [line for pid, line in last.items() if pid not in drop]
    removed = len(raw) - len(kept)
    if removed == 0:
        return 0
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as f:
        f.writelines(kept)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)
    return removed


def append(path: str | os.PathLike[str], record: dict[str, Any]) -> None:
    """Append one record as a single write, then flush and fsync."""
    line = json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n"
    try:
        with open(path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:  # a full disk: name the file (the pair is redone by the next run)
        raise OSError(e.errno, f"cannot append pair {record.get('pair_id')} ({e.strerror})", str(path)) from None


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
