"""The pairs of a curated folder as exports see them: validated manifest records, sample keys, and the
trainer shape checks (4k+1 frames, sides divisible by 16).

Everything is checked before an export writes anything: a folder that is not a curated dataset, a
manifest line missing a field, or a pair whose files are gone raises `ExportError` naming the folder,
the pair and the file.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsError, MorphgsWarning
from morphgs.curation import manifest

__all__ = ["ExportError", "PairEntry", "check_trainer_shapes", "load_pairs", "sample_key"]

SPLITS = ("train", "test")
_REQUIRED = ("split", "frames", "resolution", "paths")
_REQUIRED_PATHS = ("cameras", "clean", "corrupted")


class ExportError(MorphgsError):
    """A curated folder that cannot be exported, or an export that would overwrite one (names the path)."""


@dataclass(frozen=True)
class PairEntry:
    """One finished pair of a curated folder, with absolute paths.

    `clean`/`corrupted` are frame folders (`00000.png` ...) or MP4 files (`video` True); the depth
    folders hold `00000.depth.exr` ... when the pair was curated with --depth.
    """

    pair_id: str
    key: str
    split: str
    frames: int
    width: int
    height: int
    video: bool
    clean: Path
    corrupted: Path
    cameras: Path
    clean_depth: Path | None
    corrupted_depth: Path | None
    record: dict[str, Any]

    @property
    def has_depth(self) -> bool:
        return self.clean_depth is not None and self.corrupted_depth is not None

    def frame_path(self, side: str, index: int) -> Path:
        """The PNG of frame `index` of `side` ("clean" or "corrupted"); frame pairs only."""
        return (self.clean if side == "clean" else self.corrupted) / f"{index:05d}.png"

    def depth_paths(self, side: str) -> list[Path]:
        folder = self.clean_depth if side == "clean" else self.corrupted_depth
        if folder is None:
            raise ExportError(f"pair {self.pair_id} has no depth maps (curate with --depth)")
        return [folder / f"{i:05d}.depth.exr" for i in range(self.frames)]


def sample_key(pair_id: str) -> str:
    """A file-name and WebDataset-safe key for a pair id: `scene/config/0001` -> `scene_config_0001`.

    Only letters, digits, `_` and `-` survive (WebDataset splits a member name at its first dot, so a
    key holds none); every other run of characters becomes `-`.
    """
    return re.sub(r"[^A-Za-z0-9_-]+", "-", pair_id.replace("/", "_")).strip("-") or "pair"


def _unique_keys(pair_ids: Sequence[str]) -> dict[str, str]:
    """Keys for sorted pair ids; two ids that sanitise to one key both get a hash suffix."""
    keys = {pid: sample_key(pid) for pid in pair_ids}
    count: dict[str, int] = {}
    for k in keys.values():
        count[k] = count.get(k, 0) + 1
    for pid, k in keys.items():
        if count[k] > 1:
            keys[pid] = f"{k}-{hashlib.sha256(pid.encode()).hexdigest()[:10]}"
    return keys


def _field(root: Path, pid: str, rec: dict[str, Any], name: str) -> Any:
    if name not in rec:
        raise ExportError(f"{root}: manifest line of pair {pid} has no {name!r} field")
    return rec[name]


def _entry(root: Path, pid: str, key: str, rec: dict[str, Any]) -> PairEntry:
    for name in _REQUIRED:
        _field(root, pid, rec, name)
    paths = rec["paths"]
    if not isinstance(paths, dict):
        raise ExportError(f"{root}: manifest line of pair {pid}: 'paths' is not an object")
    for name in _REQUIRED_PATHS:
        if not isinstance(paths.get(name), str):
            raise ExportError(f"{root}: manifest line of pair {pid}: paths has no {name!r} entry")
    try:
        frames = int(rec["frames"])
        width, height = (int(v) for v in rec["resolution"])
    except (TypeError, ValueError):
        raise ExportError(f"{root}: manifest line of pair {pid}: 'frames' must be a number and "
                          f"'resolution' [W, H], got {rec['frames']!r} and {rec['resolution']!r}") from None
    if frames < 1 or width < 1 or height < 1:
        raise ExportError(f"{root}: manifest line of pair {pid}: {frames} frames of {width}x{height}")
    split = rec["split"]
    if split not in SPLITS:
        raise ExportError(f"{root}: manifest line of pair {pid}: split {split!r} is not train or test")
    try:
        files = manifest.expected_files(rec)
    except (KeyError, TypeError, ValueError) as e:
        raise ExportError(f"{root}: manifest line of pair {pid}: paths lack {e}") from None
    for rel in files:
        if not (root / rel).is_file():
            raise ExportError(f"{root}: pair {pid} lists {rel}, which is missing "
                              "(was the folder moved or partly deleted? rerun morphgs curate to redo it)")
    depth = bool(rec.get("depth"))
    return PairEntry(
        pair_id=pid, key=key, split=split, frames=frames, width=width, height=height,
        video=bool(rec.get("video")), clean=root / paths["clean"], corrupted=root / paths["corrupted"],
        cameras=root / paths["cameras"],
        clean_depth=root / paths["clean_depth"] if depth else None,
        corrupted_depth=root / paths["corrupted_depth"] if depth else None,
        record=rec,
    )


def _check_frame_size(entry: PairEntry) -> None:
    """The first PNG of each side has the manifest's size (reads the image header only)."""
    from PIL import Image, UnidentifiedImageError

    for side in ("clean", "corrupted"):
        path = entry.frame_path(side, 0)
        try:
            with Image.open(path) as im:
                size = im.size
        except (UnidentifiedImageError, OSError) as e:
            raise ExportError(f"{path}: not a readable PNG ({e})") from None
        if size != (entry.width, entry.height):
            raise ExportError(f"{path}: frame of {size[0]}x{size[1]}, but the manifest says pair "
                              f"{entry.pair_id} is {entry.width}x{entry.height}")


def load_pairs(
    dataset: str | os.PathLike[str],
    *,
    configs: Sequence[str] | None = None,
) -> tuple[Path, list[PairEntry]]:
    """The checked pairs of a curated folder, sorted by split (train first) then key.

    Args:
        dataset: a `morphgs curate` output folder (holding manifest*.jsonl).
        configs: only pairs of these config names (all by default).

    Returns:
        (the folder, resolved; its pairs).

    Raises:
        FileNotFoundError: no such folder.
        ExportError: not a curated folder, no pairs (of these configs), a manifest line missing a
            field, or a pair whose files are missing or whose frames are not the manifest's size.
    """
    root = Path(dataset).resolve()
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such folder")
    if not root.is_dir():
        raise ExportError(f"{root}: not a folder (give the folder morphgs curate wrote)")
    if not any(root.glob("manifest*.jsonl")):
        raise ExportError(f"{root}: not a curated folder (no manifest*.jsonl; make one with morphgs curate)")
    recs = manifest.load(root)
    if configs:
        recs = {k: r for k, r in recs.items() if r.get("config_name") in configs}
    if not recs:
        which = f" of config {', '.join(configs)}" if configs else ""
        raise ExportError(f"{root}: no finished pairs{which} in manifest*.jsonl")
    keys = _unique_keys(sorted(recs))
    entries = [_entry(root, pid, keys[pid], recs[pid]) for pid in sorted(recs)]
    for e in entries:
        if not e.video:
            _check_frame_size(e)
    entries.sort(key=lambda e: (SPLITS.index(e.split), e.key))
    return root, entries


def encoded_size(width: int, height: int) -> tuple[int, int]:
    """The size of an H.264 yuv420p MP4 of frames of this size (odd sides are padded by one pixel)."""
    return width + width % 2, height + height % 2


def _caller_level() -> int:
    """The `stacklevel` that makes a warning raised in this package point at the first caller
    outside it (the user's line), however many morphgs frames are in between."""
    pkg = str(Path(__file__).resolve().parents[1])
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(pkg):
        frame, level = frame.f_back, level + 1  # type: ignore[assignment]
    return level


def check_trainer_shapes(entries: Sequence[PairEntry], *, trainer: str) -> list[str]:
    """Warn (`MorphgsWarning`, at most one per rule) about pairs the video trainers would trim or crop.

    Wan-based trainers encode 4k+1 frames (1 + 4 per latent frame; DiffSynth's `LoadVideo` drops the
    rest) at sizes divisible by 16 (DiffSynth's default `height/width_division_factor`; VAE stride 8
    times patch 2), so other counts and sizes lose frames or pixels.

    Returns:
        The warning messages (also emitted).
    """
    msgs = []
    frames = sorted({e.frames for e in entries if (e.frames - 1) % 4 != 0})
    if frames:
        n = sum(1 for e in entries if (e.frames - 1) % 4 != 0)
        msgs.append(f"{n} of {len(entries)} pairs have {', '.join(map(str, frames))} frames, not 4k+1 "
                    f"(e.g. 17, 49, 81): the Wan VAE behind {trainer} takes 4k+1 frames and the rest are dropped "
                    "(curate with --frames 49)")
    sizes = sorted({encoded_size(e.width, e.height) for e in entries
                    if any(v % 16 for v in encoded_size(e.width, e.height))})
    if sizes:
        n = sum(1 for e in entries if any(v % 16 for v in encoded_size(e.width, e.height)))
        txt = ", ".join(f"{w}x{h}" for w, h in sizes)
        msgs.append(f"{n} of {len(entries)} pairs are {txt}, not divisible by 16: {trainer} crops or "
                    "resizes them (curate with --size 832x480)")
    level = _caller_level()
    for m in msgs:
        warnings.warn(m, MorphgsWarning, stacklevel=level)
    return msgs
