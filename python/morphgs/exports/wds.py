"""WebDataset export: tar shards of whole pairs, one sample per pair, and a JSON shard index.

A sample is the tar members sharing the pair's key (WebDataset groups members by the name up to the
first dot): `KEY.clean.mp4`, `KEY.corrupted.mp4`, `KEY.json` (cameras, the manifest record) and, for
pairs curated with --depth, `KEY.depth.npz` (arrays `clean` and `corrupted`, (F, H, W), float32 or
float16).
Shards hold one split each (`train-000000.tar`, ..., `test-000000.tar`) and are written in key order
with fixed member metadata, so the same curated folder gives the same shard bytes on every run.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tarfile
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs import media
from morphgs.exports.common import ExportSummary, progress_bar, write_export_json, write_json
from morphgs.exports.encode import clip_to_mp4, default_workers, ordered_map
from morphgs.exports.source import SPLITS, ExportError, PairEntry, check_trainer_shapes, load_pairs
from morphgs.exports.staging import staged_dir

__all__ = ["DEFAULT_SHARD_BYTES", "depth_npz", "export_webdataset", "parse_shard_size"]

DEFAULT_SHARD_BYTES = 512 * 10**6
_UNITS = {"b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "kib": 2**10, "mib": 2**20, "gib": 2**30}


def parse_shard_size(text: str) -> tuple[int | None, int | None]:
    """`"512MB"` -> (512000000, None); `"100samples"` -> (None, 100). Units: B, KB, MB, GB, KiB, MiB,
    GiB (case-insensitive) or `samples`.

    Raises:
        ValueError: no unit, an unknown unit, or a size below 1.
    """
    t = text.strip().lower().replace(" ", "")
    num = t.rstrip("abcdefghijklmnopqrstuvwxyz")
    unit = t[len(num):]
    try:
        value = float(num)
    except ValueError:
        raise ValueError(f"shard size must look like 512MB, 2GB or 100samples, got {text!r}") from None
    if unit in ("samples", "sample"):
        if value < 1 or value != int(value):
            raise ValueError(f"shard size in samples must be a whole number >= 1, got {text!r}")
        return None, int(value)
    if unit not in _UNITS:
        raise ValueError(f"shard size needs a unit (B, KB, MB, GB, KiB, MiB, GiB or samples), got {text!r}")
    size = int(value * _UNITS[unit])
    if size < 1:
        raise ValueError(f"shard size must be at least 1 byte, got {text!r}")
    return size, None


def depth_npz(clean: np.ndarray, corrupted: np.ndarray, *, dtype: str = "float32") -> bytes:
    """An .npz (what `np.load` reads) of two depth stacks with fixed zip timestamps (numpy's own
    savez stamps the current time, so its bytes change run to run).

    float32 is stored as is: rendered depth barely compresses (deflate saves 18 % of a 49-frame
    832x480 stack for 3.3 s of CPU). float16 (ArtiFixer's choice; relative error <= 2^-11) is
    deflated at level 1: 4.4x smaller than float32 in about 1 s.

    Raises:
        ExportError: an unknown dtype, or a float16 export of depths float16 cannot hold (> 65504).
    """
    if dtype not in ("float32", "float16"):
        raise ExportError(f"depth dtype must be float32 or float16, got {dtype!r}")
    buf = io.BytesIO()
    method = zipfile.ZIP_STORED if dtype == "float32" else zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(buf, "w", compression=method, compresslevel=1) as zf:
        for name, arr in (("clean", clean), ("corrupted", corrupted)):
            peak = float(np.max(np.abs(arr[np.isfinite(arr)]), initial=0.0))
            if dtype == "float16" and peak > 65504:
                raise ExportError(f"{name} depth reaches {peak:.6g}, past float16's 65504; export depth as float32")
            npy = io.BytesIO()
            np.lib.format.write_array(npy, np.ascontiguousarray(arr, dtype=dtype), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(info, npy.getbuffer(), compress_type=method, compresslevel=1)
    return buf.getvalue()


def _sample_json(entry: PairEntry, fps: float) -> bytes:
    cameras = json.loads(entry.cameras.read_text(encoding="utf-8"))
    obj = {"key": entry.key, "pair_id": entry.pair_id, "split": entry.split, "frames": entry.frames,
           "width": entry.width, "height": entry.height, "fps": None if entry.video else fps,
           "depth": entry.has_depth, "cameras": cameras, "manifest": entry.record}
    return (json.dumps(obj, sort_keys=True, separators=(",", ":")) + "\n").encode()


class _ShardWriter:
    """Appends samples to `SPLIT-NNNNNN.tar` files, starting a new shard before one would pass
    `max_bytes` or hold `max_samples` (a sample larger than `max_bytes` gets a shard of its own)."""

    def __init__(self, folder: Path, split: str, max_bytes: int | None, max_samples: int | None) -> None:
        self.folder, self.split, self.max_bytes, self.max_samples = folder, split, max_bytes, max_samples
        self.shards: list[dict[str, Any]] = []
        self.tar: tarfile.TarFile | None = None
        self.size = 0

    @staticmethod
    def _info(name: str, size: int) -> tarfile.TarInfo:
        info = tarfile.TarInfo(name)
        info.size, info.mtime, info.mode = size, 0, 0o644
        info.uid = info.gid = 0
        info.uname = info.gname = ""
        return info

    def _file_size(self, content: int) -> int:
        """A tar's size on disk: its members, two zero blocks, padded to tarfile's 10240-byte records."""
        return -(-(content + 2 * tarfile.BLOCKSIZE) // tarfile.RECORDSIZE) * tarfile.RECORDSIZE

    def add(self, key: str, members: Sequence[tuple[str, bytes]]) -> None:
        infos = [self._info(name, len(data)) for name, data in members]
        need = sum(len(i.tobuf(tarfile.PAX_FORMAT, tarfile.ENCODING, "surrogateescape"))
                   + -(-i.size // tarfile.BLOCKSIZE) * tarfile.BLOCKSIZE for i in infos)
        cur = self.shards[-1] if self.shards else None
        full = cur is not None and (
            (self.max_samples is not None and cur["samples"] >= self.max_samples)
            or (self.max_bytes is not None and self._file_size(self.size + need) > self.max_bytes))
        if self.tar is None or full:
            self._open()
        assert self.tar is not None
        for info, (_, data) in zip(infos, members):
            self.tar.addfile(info, io.BytesIO(data))
        self.size += need
        self.shards[-1]["samples"] += 1
        self.shards[-1]["keys"].append(key)

    def _open(self) -> None:
        self.close()
        name = f"{self.split}-{len(self.shards):06d}.tar"
        self.tar = tarfile.open(self.folder / name, "w", format=tarfile.PAX_FORMAT)
        self.size = 0
        self.shards.append({"name": name, "split": self.split, "samples": 0, "keys": []})

    def close(self) -> None:
        if self.tar is not None:
            self.tar.close()
            self.tar = None
            self.shards[-1]["bytes"] = (self.folder / self.shards[-1]["name"]).stat().st_size


def _pattern(split: str, n: int) -> str:
    """The brace pattern `webdataset.WebDataset` expands to a split's shards."""
    return f"{split}-000000.tar" if n == 1 else f"{split}-{{000000..{n - 1:06d}}}.tar"


def export_webdataset(
    dataset: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    configs: Sequence[str] | None = None,
    shard_bytes: int | None = DEFAULT_SHARD_BYTES,
    shard_samples: int | None = None,
    depth: bool | None = None,
    depth_dtype: str = "float32",
    fps: float = 16,
    crf: int = 18,
    workers: int | None = None,
    progress: bool = True,
) -> ExportSummary:
    """WebDataset tar shards of a curated folder, one sample per pair, and `OUT/index.json`.

    Read them back with `webdataset.WebDataset(OUT + "/" + index["splits"]["train"]["pattern"],
    shardshuffle=False)`; each sample has `clean.mp4`, `corrupted.mp4`, `json` and maybe `depth.npz`.

    Args:
        dataset: a `morphgs curate` folder. out: the export folder (must not exist or be empty).
        overwrite: replace an existing export at `out`.
        configs: only pairs of these config names.
        shard_bytes: start a new shard before one passes this many bytes (None: no byte limit).
        shard_samples: at most this many samples per shard (None: no count limit).
        depth: include `depth.npz` (None: when every pair has depth maps).
        depth_dtype: "float32" (exact, stored uncompressed) or "float16" (4.4x smaller, deflated).
        fps, crf: H.264 frame rate and quality of the MP4s encoded from frames.
        workers: clips encoded at once (the native thread count by default).
        progress: a progress bar on stderr.

    Returns:
        An `ExportSummary`; `extra["shards"]` lists the shards.

    Raises:
        FileNotFoundError, ExportError: see `load_pairs` and `staged_dir`; depth asked for but missing;
        a shard size below 1.
    """
    if depth_dtype not in ("float32", "float16"):
        raise ExportError(f"depth dtype must be float32 or float16, got {depth_dtype!r}")
    if (shard_bytes is not None and shard_bytes < 1) or (shard_samples is not None and shard_samples < 1):
        raise ExportError(f"shard size must be at least 1, got {shard_bytes} bytes, {shard_samples} samples")
    t0 = time.perf_counter()
    root, entries = load_pairs(dataset, configs=configs)
    if depth is None:
        depth = all(e.has_depth for e in entries)
    elif depth and not all(e.has_depth for e in entries):
        missing = next(e for e in entries if not e.has_depth)
        raise ExportError(f"{root}: depth asked for, but pair {missing.pair_id} has no depth maps "
                          "(curate with --depth)")
    msgs = check_trainer_shapes(entries, trainer="Wan-style video training")
    parts = ["clean.mp4", "corrupted.mp4", "json"] + (["depth.npz"] if depth else [])

    with staged_dir(out, root, overwrite=overwrite) as tmp:
        work = tmp / ".work"

        def make(job: tuple[PairEntry, str]) -> bytes:
            e, part = job
            if part == "json":
                return _sample_json(e, fps)
            if part == "depth.npz":
                try:
                    return depth_npz(media.read_depth(e.depth_paths("clean")),
                                     media.read_depth(e.depth_paths("corrupted")), dtype=depth_dtype)
                except ExportError as err:
                    raise ExportError(f"pair {e.pair_id}: {err}") from None
            side = part.split(".")[0]
            path = clip_to_mp4(e, side, work / f"{e.key}.{part}", fps=fps, crf=crf)
            data = path.read_bytes()
            path.unlink()
            return data

        jobs = [(e, part) for e in entries for part in parts]
        writers = {s: _ShardWriter(tmp, s, shard_bytes, shard_samples) for s in SPLITS}
        bar = progress_bar(len(entries), enabled=progress, unit="pair")
        members: list[tuple[str, bytes]] = []
        try:
            for (e, part), data in zip(jobs, ordered_map(make, jobs, workers=workers or default_workers())):
                members.append((f"{e.key}.{part}", data))
                if len(members) == len(parts):
                    writers[e.split].add(e.key, members)
                    members = []
                    bar.update(1)
        finally:
            bar.close()
            for w in writers.values():
                w.close()
        shutil.rmtree(work, ignore_errors=True)
        shards = [s for sp in SPLITS for s in writers[sp].shards]
        splits = {sp: {"samples": sum(s["samples"] for s in writers[sp].shards), "shards": len(writers[sp].shards),
                       "pattern": _pattern(sp, len(writers[sp].shards))}
                  for sp in SPLITS if writers[sp].shards}
        write_json(tmp / "index.json", {"format": "webdataset", "members": parts, "splits": splits,
                                        "depth_dtype": depth_dtype if depth else None,
                                        "shards": shards,
                                        "shard_size": {"bytes": shard_bytes, "samples": shard_samples}})
        counts = write_export_json(tmp, fmt="webdataset", source=root, entries=entries, warnings=msgs,
                                   options={"shard_bytes": shard_bytes, "shard_samples": shard_samples,
                                            "depth": depth, "depth_dtype": depth_dtype, "fps": fps, "crf": crf})
    return ExportSummary("webdataset", Path(out), counts, msgs,
                         {"shards": shards, "seconds": time.perf_counter() - t0})
