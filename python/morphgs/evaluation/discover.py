"""Pairing predicted clips with their ground truth on disk (what `morphgs eval PRED GT` reads).

A *clip* is a video file or a folder that holds frames itself. PRED and GT are either two clips,
or two folders of clips matched by their path relative to the folder, a video's suffix dropped
(`PRED/scene/a.mp4` pairs with `GT/scene/a/` or `GT/scene/a.mp4`). Depth folders mirror the
same layout (`DEPTH/scene/a/*.exr`) or, for two clips, are one folder of EXRs each.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from morphgs import media
from morphgs.evaluation.core import ClipPair, EvalError

__all__ = ["discover_pairs", "find_clips", "is_clip", "read_cameras"]


def is_clip(path: Path) -> bool:
    """A video file, or a folder holding frame images itself."""
    if path.is_file():
        return media.is_video(path)
    if not path.is_dir():
        return False
    return any(p.suffix.lower() in media.IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
               for p in path.iterdir())


def find_clips(root: Path) -> dict[str, Path]:
    """{relative key: clip path} of every clip under `root` (clip folders are not searched further)."""
    found: dict[str, Path] = {}

    def walk(d: Path) -> None:
        for p in sorted(d.iterdir()):
            if p.name.startswith("."):
                continue
            if p.is_file() and media.is_video(p):
                key = p.relative_to(root).with_suffix("").as_posix()
            elif p.is_dir() and is_clip(p):
                key = p.relative_to(root).as_posix()
            elif p.is_dir():
                walk(p)
                continue
            else:
                continue
            if key in found:
                raise EvalError(f"{root}: two clips named {key!r} ({found[key].name} and {p.name})")
            found[key] = p

    walk(root)
    return found


def read_cameras(path: str | os.PathLike[str]) -> Any:
    """`morphgs.Cameras` from a cameras.json (as `morphgs curate` writes it).

    Raises:
        FileNotFoundError: no such file. EvalError: not a cameras file.
    """
    from morphgs.camera import Cameras

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such cameras file")
    try:
        return Cameras.from_dict(json.loads(p.read_text(encoding="utf-8")))
    except (ValueError, TypeError, KeyError) as e:
        raise EvalError(f"{p}: not a cameras file ({e})") from None


def _exists(path: str | os.PathLike[str], what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder ({what})")
    return p


def discover_pairs(
    pred: str | os.PathLike[str],
    gt: str | os.PathLike[str],
    *,
    depth_pred: str | os.PathLike[str] | None = None,
    depth_gt: str | os.PathLike[str] | None = None,
    cameras: str | os.PathLike[str] | None = None,
    name: str | None = None,
    label: str = "pred",
) -> list[ClipPair]:
    """The clip pairs of PRED and GT (two clips, or two folders of clips; see the module).

    Args:
        pred, gt: clips or folders of clips.
        depth_pred, depth_gt: depth folders (one per clip, or trees mirroring PRED and GT).
        cameras: a cameras.json of the GT frames (two clips only): exact flow references.
        name: the clip's name when PRED and GT are single clips (default: GT's name).
        label: the label of every pair.

    Raises:
        FileNotFoundError: a missing path. EvalError: one clip against a folder of clips, clips
            present on one side only, no clips at all, a missing depth folder.
    """
    p, g = _exists(pred, "PRED"), _exists(gt, "GT")
    dp = None if depth_pred is None else _exists(depth_pred, "--depth-pred")
    dg = None if depth_gt is None else _exists(depth_gt, "--depth-gt")
    if is_clip(g) or is_clip(p):
        if not (is_clip(g) and is_clip(p)):
            one, other = (g, p) if is_clip(g) else (p, g)
            if other.is_dir() and not find_clips(other):
                raise EvalError(f"{other}: no frames (.png, .jpg) or clips in this folder")
            raise EvalError(f"{one} is a clip but {other} is a folder of clips (pass two clips or two folders of clips)")
        cams = None if cameras is None else read_cameras(cameras)
        return [ClipPair(name or (g.stem if g.is_file() else g.name), p, g, dp, dg, cams, label)]
    if cameras is not None:
        raise EvalError("--cameras applies to a single clip pair, not to folders of clips")
    gt_clips, pred_clips = find_clips(g), find_clips(p)
    if not gt_clips:
        raise EvalError(f"{g}: no clips (folders of frames or videos) in this folder")
    missing = sorted(set(gt_clips) - set(pred_clips))
    extra = sorted(set(pred_clips) - set(gt_clips))
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"no prediction for {len(missing)} GT clip(s) ({', '.join(missing[:5])})")
        if extra:
            parts.append(f"no GT for {len(extra)} predicted clip(s) ({', '.join(extra[:5])})")
        raise EvalError(f"{p} vs {g}: {'; '.join(parts)}")
    out = []
    for key in sorted(gt_clips):
        depths: list[Path | None] = []
        for root, what in ((dp, "--depth-pred"), (dg, "--depth-gt")):
            if root is None:
                depths.append(None)
                continue
            d = root / key
            if not d.is_dir():
                raise EvalError(f"{what} {root}: no depth folder {key!r} for clip {key!r}")
            depths.append(d)
        out.append(ClipPair(key, pred_clips[key], gt_clips[key], depths[0], depths[1], None, label))
    return out
