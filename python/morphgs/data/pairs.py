"""`PairDataset`: clips of a curated folder (`morphgs curate` output) as torch tensors.

Every `manifest*.jsonl` of the folder is read (shards merged, `morphgs.curation.manifest.load`);
the manifest's `split` field decides train/test. A pair is read through `morphgs.media` (PNG
frame folders or MP4s), only the F frames a sample needs.

A sample is a dict:

| key | value |
|---|---|
| `corrupted`, `clean` | float32 (3, F, H, W) in [-1, 1] |
| `reference` | float32 (3, R, H, W) clean frames from outside the window (`reference=R > 0`) |
| `clean_depth`, `corrupted_depth` | float32 (1, F, H, W), expected depth (`depth=True`; pairs curated with `--depth`) |
| `K`, `world_to_camera` | float64 (F, 3, 3) intrinsics of the windowed frames, (F, 4, 4) (`cameras=True`) |
| `pair_id`, `start`, `y0`, `x0`, `flip`, `seed` | where the window came from |

The default DataLoader collation stacks them into (B, C, F, H, W).

Keys: `dataset[i]` (a plain index) draws the window at random from torch's generator in training
(the PyTorch convention: DataLoader seeds each worker) and takes the centre in evaluation;
`dataset[(i, seed)]` draws it from `seed` (see `morphgs.data.seeds`), which is what the training
loop's sampler passes, so a resumed or distributed run reads exactly the same windows.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from morphgs import media
from morphgs._core import MorphgsError
from morphgs.data.seeds import rng
from morphgs.data.window import Window, adjust_intrinsics, choose_window

__all__ = ["DatasetError", "PairDataset", "PairRecord"]


class DatasetError(MorphgsError):
    """A curated folder that cannot serve as training data (names the folder, pair and file)."""


@dataclass(frozen=True)
class PairRecord:
    """One pair of the dataset, resolved to absolute paths."""

    pair_id: str
    split: str
    clean: Path
    corrupted: Path
    frames: int
    height: int
    width: int
    cameras: Path | None = None
    clean_depth: Path | None = None
    corrupted_depth: Path | None = None
    config_name: str = ""


def _size2(value: Sequence[int] | int | None, name: str) -> tuple[int, int] | None:
    if value is None:
        return None
    if isinstance(value, int):
        value = (value, value)
    h, w = (int(v) for v in value)
    if h < 1 or w < 1:
        raise ValueError(f"{name} must be positive (H, W), got {tuple(value)}")
    return h, w


def _count_frames(path: Path, record: dict[str, Any]) -> int:
    if path.is_dir():
        return len(media.frame_paths(path))
    return int(record["frames"])  # a video: trust the manifest; reading checks the real count


def _resolve(root: Path, rec: dict[str, Any], manifest: str) -> PairRecord:
    pid = rec.get("pair_id", "?")
    try:
        paths = rec["paths"]
        clean = root / paths["clean"]
        corrupted = root / paths["corrupted"]
        w, h = (int(v) for v in rec["resolution"])
        frames = int(rec["frames"])
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{manifest}: pair {pid}: malformed manifest line ({type(e).__name__}: {e})") from None
    for p in (clean, corrupted):
        if not p.exists():
            raise DatasetError(f"{manifest}: pair {pid}: {p} is missing (the manifest lists it)")
    depth = {}
    for side in ("clean_depth", "corrupted_depth"):
        if side in paths:
            depth[side] = root / paths[side]
    cams = root / paths["cameras"] if "cameras" in paths else None
    return PairRecord(str(pid), str(rec.get("split", "train")), clean, corrupted, frames, h, w, cams,
                      depth.get("clean_depth"), depth.get("corrupted_depth"), str(rec.get("config_name", "")))


def load_records(root: str | os.PathLike[str]) -> list[PairRecord]:
    """Every finished pair of a curated folder (all splits), sorted by pair id.

    Raises:
        FileNotFoundError: no such folder. DatasetError: no manifest, no pairs, or a line whose
        files are missing (named).
    """
    from morphgs.curation import manifest

    d = Path(root)
    if not d.exists():
        raise FileNotFoundError(f"{d}: no such dataset folder")
    if not d.is_dir():
        raise DatasetError(f"{d}: not a folder (a dataset is a folder written by morphgs curate)")
    manifests = sorted(d.glob("manifest*.jsonl"))
    if not manifests:
        raise DatasetError(f"{d}: no manifest*.jsonl: not a curated folder (morphgs curate writes one)")
    recs = manifest.load(d)
    if not recs:
        raise DatasetError(f"{d}: {', '.join(m.name for m in manifests)} list no finished pairs")
    where = f"{d}/manifest*.jsonl"
    return [_resolve(d, recs[k], where) for k in sorted(recs)]


class PairDataset(torch.utils.data.Dataset):  # type: ignore[type-arg]
    """Clips of F consecutive frames from the pairs of one split of a curated folder.

    Args:
        root: the curated folder.
        split: "train" or "test" (the manifest's split), or "all".
        frames: F, frames per clip.
        size: (H, W) crop, or None for whole frames (all pairs must then share a size).
        train: random window (temporal offset, crop, flip) when True; centre clip when False.
            Defaults to split == "train".
        flip: allow random left-right flips in training.
        resize: (H, W) to resize whole frames to before cropping (antialiased), or None.
        reference: R clean reference frames per sample, evenly spread over the pair's frames
            outside the window (the pair must have at least F + R frames).
        depth: also return the pairs' depth maps (curated with --depth).
        cameras: also return the windowed frames' intrinsics and world-to-camera matrices.
        configs: only pairs with these config names (None: all).

    Raises:
        FileNotFoundError, DatasetError: see `load_records`; also a split with no pairs, a clip
        shorter than F (+ R), a crop larger than the frames, depth asked of pairs without it.
        Reading a sample raises media.MediaError for unreadable or mismatched frames (names the file).
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        split: str = "train",
        frames: int = 16,
        size: Sequence[int] | int | None = None,
        *,
        train: bool | None = None,
        flip: bool = False,
        resize: Sequence[int] | int | None = None,
        reference: int = 0,
        depth: bool = False,
        cameras: bool = False,
        configs: Sequence[str] | None = None,
    ) -> None:
        if split not in ("train", "test", "all"):
            raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
        if frames < 1 or reference < 0:
            raise ValueError(f"need frames >= 1 and reference >= 0, got {frames}, {reference}")
        self.root = Path(root)
        self.split = split
        self.frames = int(frames)
        self.size = _size2(size, "size")
        self.resize = _size2(resize, "resize")
        self.train = (split == "train") if train is None else bool(train)
        self.flip = bool(flip)
        self.reference = int(reference)
        self.depth = bool(depth)
        self.cameras = bool(cameras)
        records = load_records(self.root)
        chosen = [r for r in records if (split == "all" or r.split == split)
                  and (configs is None or r.config_name in configs)]
        if not chosen:
            counts = {s: sum(r.split == s for r in records) for s in ("train", "test")}
            raise DatasetError(f"{self.root}: no pairs in split {split!r}"
                               + (f" with configs {list(configs)}" if configs is not None else "")
                               + f" (the manifest has {counts['train']} train and {counts['test']} test pairs)")
        self.records = chosen
        self._counts = [self._check(r) for r in chosen]

    def _check(self, r: PairRecord) -> int:
        n = _count_frames(r.clean, {"frames": r.frames})
        n_c = _count_frames(r.corrupted, {"frames": r.frames})
        if n != n_c:
            raise DatasetError(f"pair {r.pair_id}: {r.clean} has {n} frames but {r.corrupted} has {n_c}")
        need = self.frames + self.reference
        if n < need:
            what = f"{self.frames} frames" + (f" + {self.reference} reference frames" if self.reference else "")
            raise DatasetError(f"pair {r.pair_id}: clip {r.clean} has {n} frames, shorter than the {what} asked for")
        h, w = self.resize if self.resize is not None else (r.height, r.width)
        if self.size is not None and (self.size[0] > h or self.size[1] > w):
            raise DatasetError(f"pair {r.pair_id}: crop {self.size[0]}x{self.size[1]} (HxW) does not fit its "
                               f"{h}x{w} frames ({r.clean})")
        if self.depth and (r.clean_depth is None or r.corrupted_depth is None):
            raise DatasetError(f"pair {r.pair_id}: depth asked for, but the manifest lists no depth maps "
                               "(curate with --depth)")
        if self.cameras and (r.cameras is None or not r.cameras.is_file()):
            raise DatasetError(f"pair {r.pair_id}: cameras asked for, but {r.cameras} is missing")
        return n

    def __len__(self) -> int:
        return len(self.records)

    def window(self, index: int, seed: int | None) -> Window:
        """The window sample `index` takes: from `seed` in training, the centre in evaluation."""
        r = self.records[index]
        gen = rng(seed) if (self.train and seed is not None) else None
        return choose_window(self._counts[index], (r.height, r.width), frames=self.frames, crop=self.size,
                             resize=self.resize, rng=gen, flip=self.flip)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        if isinstance(key, tuple):
            index, seed = int(key[0]), int(key[1])
        else:
            index = int(key)
            seed = int(torch.randint(0, 2**62, (1,)).item()) if self.train else 0
        if not 0 <= index < len(self.records):
            raise IndexError(f"index {index} out of range for {len(self.records)} pairs")
        r = self.records[index]
        win = self.window(index, seed)
        out: dict[str, Any] = {"pair_id": r.pair_id, "start": win.start, "y0": win.y0, "x0": win.x0,
                               "flip": win.flip, "seed": seed}
        clean = media.read_clip(r.clean, start=win.start, count=win.frames)
        corrupted = media.read_clip(r.corrupted, start=win.start, count=win.frames)
        if clean.shape != corrupted.shape:
            raise media.MediaError(f"pair {r.pair_id}: clean frames {r.clean} are {clean.shape[2]}x{clean.shape[1]}"
                                   f" but corrupted frames {r.corrupted} are {corrupted.shape[2]}x{corrupted.shape[1]}")
        if clean.shape[1:3] != (r.height, r.width):
            raise media.MediaError(f"pair {r.pair_id}: frames of {r.clean} are {clean.shape[2]}x{clean.shape[1]}, "
                                   f"the manifest says {r.width}x{r.height}")
        out["clean"] = frames_to_tensor(clean, win)
        out["corrupted"] = frames_to_tensor(corrupted, win)
        if self.reference:
            idx = reference_indices(self._counts[index], win, self.reference)
            ref = np.stack([media.read_clip(r.clean, start=i, count=1)[0] for i in idx])
            out["reference"] = frames_to_tensor(ref, win)
        if self.depth:
            for side, folder in (("clean_depth", r.clean_depth), ("corrupted_depth", r.corrupted_depth)):
                assert folder is not None
                files = [folder / f"{i:05d}.depth.exr" for i in range(win.start, win.start + win.frames)]
                d = media.read_depth(files)
                out[side] = frames_to_tensor(d[..., None], win, scale=False)
        if self.cameras:
            assert r.cameras is not None
            K, w2c = _read_cameras(r.cameras, win)
            out["K"] = torch.from_numpy(adjust_intrinsics(K, win, (r.height, r.width)))
            out["world_to_camera"] = torch.from_numpy(w2c)
        return out


def reference_indices(n_frames: int, win: Window, count: int) -> list[int]:
    """`count` frame indices evenly spread over the frames outside the window."""
    outside = [i for i in range(n_frames) if not win.start <= i < win.start + win.frames]
    if len(outside) < count:
        raise DatasetError(f"{count} reference frames asked for, only {len(outside)} lie outside the window")
    pos = np.linspace(0, len(outside) - 1, count)
    return [outside[int(round(p))] for p in pos]


def _read_cameras(path: Path, win: Window) -> tuple[np.ndarray, np.ndarray]:
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
        K = np.asarray(d["K"], dtype=np.float64)[win.start:win.start + win.frames]
        w2c = np.asarray(d["world_to_camera"], dtype=np.float64)[win.start:win.start + win.frames]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DatasetError(f"{path}: not a readable cameras.json ({type(e).__name__}: {e})") from None
    if K.shape != (win.frames, 3, 3) or w2c.shape != (win.frames, 4, 4):
        raise DatasetError(f"{path}: K/world_to_camera do not cover frames {win.start}..{win.start + win.frames - 1}")
    return K, w2c


def frames_to_tensor(frames: np.ndarray, win: Window, *, scale: bool = True) -> torch.Tensor:
    """(F, H, W, C) frames -> the window's (C, F, h, w) float32 tensor: resize (antialiased), crop,
    flip; uint8 / RGB values are mapped to [-1, 1] when `scale` (depth is left as is)."""
    t = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)  # (F, C, H, W)
    t = t.float()
    if scale:
        t = t / 127.5 - 1.0
    if win.resized is not None and tuple(t.shape[-2:]) != win.resized:
        t = torch.nn.functional.interpolate(t, size=win.resized, mode="bilinear", antialias=True,
                                            align_corners=False)
    t = t[..., win.y0:win.y0 + win.height, win.x0:win.x0 + win.width]
    if win.flip:
        t = t.flip(-1)
    return t.permute(1, 0, 2, 3).contiguous()
