"""`morphgs preview DIR`: a contact sheet (PNG) and an animation (GIF or MP4) of clean and
corrupted frames side by side, for a few pairs of a curated folder."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import MorphgsError
from morphgs.curation import manifest

__all__ = ["preview"]


def _frames(root: Path, rec: dict[str, Any], side: str) -> list[np.ndarray]:
    from PIL import Image

    p = root / rec["paths"][side]
    if rec.get("video"):
        import subprocess

        import imageio_ffmpeg

        w, h = rec["resolution"]
        raw = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(p), "-f", "rawvideo",
                              "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
        return list(np.frombuffer(raw, np.uint8).reshape(-1, h, w, 3))
    out = []
    for i in range(int(rec["frames"])):
        with Image.open(p / f"{i:05d}.png") as im:
            out.append(np.asarray(im.convert("RGB")))
    return out


def _thumb(a: np.ndarray, width: int) -> np.ndarray:
    from PIL import Image

    h = max(1, round(a.shape[0] * width / a.shape[1]))
    return np.asarray(Image.fromarray(a).resize((width, h), Image.Resampling.BILINEAR))


def _pick(recs: dict[str, dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """n pairs, spread over scenes and configs (round-robin by (scene, config))."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for pid in sorted(recs):
        r = recs[pid]
        groups.setdefault((r["scene"], r["config_name"]), []).append(r)
    out: list[dict[str, Any]] = []
    while len(out) < n and any(groups.values()):
        for g in groups.values():
            if g and len(out) < n:
                out.append(g.pop(0))
    return out


def preview(
    dataset: str | os.PathLike[str],
    *,
    out: str | os.PathLike[str] | None = None,
    pairs: int = 4,
    columns: int = 6,
    thumb_width: int = 208,
    animation: str = "gif",
    fps: int = 8,
) -> tuple[Path, Path]:
    """Write `contact_sheet.png` and `preview.gif` (or .mp4) for a curated folder.

    The sheet has two rows per pair (clean above corrupted) of `columns` frames spread over the
    clip; the animation plays every frame with, per pair, clean and corrupted side by side.

    Args:
        dataset: the curate output folder.
        out: where to write (default: DATASET/preview).
        pairs: how many pairs (spread over scenes and configs).
        columns: frames per row in the sheet.
        thumb_width: width of each thumbnail in pixels.
        animation: "gif" or "mp4".
        fps: animation frame rate.

    Returns:
        (sheet path, animation path).
    """
    from PIL import Image, ImageDraw

    root = Path(dataset)
    recs = manifest.load(root)
    if not recs:
        raise MorphgsError(f"{root}: no finished pairs in manifest*.jsonl")
    if animation not in ("gif", "mp4"):
        raise ValueError(f"animation must be 'gif' or 'mp4', got {animation!r}")
    chosen = _pick(recs, max(1, pairs))
    seqs = [(r, [_thumb(f, thumb_width) for f in _frames(root, r, "clean")],
             [_thumb(f, thumb_width) for f in _frames(root, r, "corrupted")]) for r in chosen]
    th, tw = seqs[0][1][0].shape[:2]
    label_h = 14
    gap = 2
    out_dir = Path(out) if out is not None else root / "preview"
    out_dir.mkdir(parents=True, exist_ok=True)

    # contact sheet
    cols = max(1, columns)
    sheet = Image.new("RGB", (cols * (tw + gap) + gap, len(seqs) * (2 * (th + gap) + label_h) + gap), "white")
    draw = ImageDraw.Draw(sheet)
    y = gap
    for r, clean, corr in seqs:
        draw.text((gap, y), f"{r['pair_id']}  [{r['split']}]  seed {r['seed']}  (top clean, bottom corrupted)",
                  fill="black")
        y += label_h
        idx = np.linspace(0, len(clean) - 1, min(cols, len(clean))).round().astype(int)
        for row, seq in enumerate((clean, corr)):
            for c, i in enumerate(idx):
                if c < len(seq) and i < len(seq):
                    sheet.paste(Image.fromarray(seq[i]), (gap + c * (tw + gap), y + row * (th + gap)))
        y += 2 * (th + gap)
    sheet_path = out_dir / "contact_sheet.png"
    sheet.save(sheet_path)

    # animation: one row per pair, clean | corrupted
    n = min(len(c) for _, c, _ in seqs)
    frames = []
    for i in range(n):
        canvas = np.full((len(seqs) * (th + gap) + gap, 2 * tw + 3 * gap, 3), 255, np.uint8)
        for k, (_, clean, corr) in enumerate(seqs):
            yy = gap + k * (th + gap)
            canvas[yy:yy + th, gap:gap + tw] = clean[i][:th, :tw]
            canvas[yy:yy + th, 2 * gap + tw:2 * gap + 2 * tw] = corr[i][:th, :tw]
        frames.append(canvas)
    if animation == "gif":
        anim_path = out_dir / "preview.gif"
        ims = [Image.fromarray(f) for f in frames]
        ims[0].save(anim_path, save_all=True, append_images=ims[1:], duration=round(1000 / fps), loop=0)
    else:
        import imageio.v2 as iio

        anim_path = out_dir / "preview.mp4"
        with iio.get_writer(str(anim_path), format="FFMPEG", mode="I", fps=fps, codec="libx264",
                            macro_block_size=1, ffmpeg_log_level="error") as w:
            for f in frames:
                w.append_data(f)  # type: ignore[attr-defined]
    return sheet_path, anim_path
