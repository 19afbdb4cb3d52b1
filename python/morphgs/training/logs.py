"""What a run writes for people to read: CSV tables of step metrics, TensorBoard scalars and
images, and before/after/target preview strips. Only the main process writes.

`RUN/logs/train.csv` (one row every `log_every` steps) and `RUN/logs/val.csv` (one row per
validation); a resumed run first drops the rows past its checkpoint, so each table reads as one
uninterrupted history. `RUN/logs/tb/` holds the TensorBoard event files, `RUN/previews/` the strips.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CsvLog", "Logs", "preview_strip"]


class CsvLog:
    """An append-only CSV table whose first column is `step`; columns are fixed by the first row."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.columns: list[str] | None = None
        if self.path.is_file():
            with open(self.path, newline="", encoding="utf-8") as f:
                header = next(csv.reader(f), None)
            self.columns = header or None

    def truncate_after(self, step: int) -> None:
        """Drop rows of steps > `step` (what a killed run logged past its last checkpoint)."""
        if not self.path.is_file():
            return
        with open(self.path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
        if not rows:
            return
        keep = [rows[0]] + [r for r in rows[1:] if r and _int(r[0]) <= step]
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            csv.writer(f).writerows(keep)
        os.replace(tmp, self.path)

    def write(self, row: Mapping[str, Any]) -> None:
        if self.columns is None:
            self.columns = list(row)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "w", newline="", encoding="utf-8") as f:
                csv.writer(f).writerow(self.columns)
        with open(self.path, "a", newline="", encoding="utf-8") as f:
            csv.writer(f).writerow([_fmt(row.get(c, "")) for c in self.columns])

    def read(self) -> list[dict[str, str]]:
        """All rows as dicts of strings."""
        if not self.path.is_file():
            return []
        with open(self.path, newline="", encoding="utf-8") as f:
            return list(csv.DictReader(f))


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        return -1


def _fmt(v: Any) -> Any:
    if isinstance(v, float):
        return repr(v)  # shortest text that reads back as the same float
    return v


class Logs:
    """CSV + TensorBoard for one run (main process only; the others get a no-op instance)."""

    def __init__(self, run_dir: str | os.PathLike[str], *, enabled: bool, tensorboard: bool = True) -> None:
        self.enabled = enabled
        self.dir = Path(run_dir) / "logs"
        self.train = CsvLog(self.dir / "train.csv")
        self.val = CsvLog(self.dir / "val.csv")
        self._tb: Any = None
        if enabled and tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:  # tensorboard not installed: CSV only
                self._tb = None
            else:
                self._tb = SummaryWriter(str(self.dir / "tb"))

    def resume_at(self, step: int) -> None:
        if self.enabled:
            self.train.truncate_after(step)
            self.val.truncate_after(step)

    def scalars(self, table: str, step: int, values: Mapping[str, float]) -> None:
        if not self.enabled:
            return
        (self.train if table == "train" else self.val).write({"step": step, **values})
        if self._tb is not None:
            for k, v in values.items():
                if isinstance(v, (int, float)) and k not in ("elapsed_s",):
                    self._tb.add_scalar(f"{table}/{k}", v, step)

    def image(self, tag: str, step: int, image: np.ndarray) -> None:
        if self.enabled and self._tb is not None:
            self._tb.add_image(tag, image, step, dataformats="HWC")

    def close(self) -> None:
        if self._tb is not None:
            self._tb.flush()
            self._tb.close()
            self._tb = None


def preview_strip(rows: Sequence[np.ndarray], *, labels: Sequence[str], frames: int = 3, gap: int = 4) -> np.ndarray:
    """Frames of several clips in rows (e.g. before / after / target): a uint8 (H', W', 3) image.

    Args:
        rows: clips as (F, H, W, 3) float in [0, 1] or uint8, all the same shape.
        labels: one per row, drawn at the left of the row when Pillow can.
        frames: frames shown per row, spread over the clip.
        gap: pixels between tiles.
    """
    clips = [np.asarray(r) for r in rows]
    clips = [c if c.dtype == np.uint8 else np.rint(np.clip(c, 0, 1) * 255).astype(np.uint8) for c in clips]
    f, h, w, _ = clips[0].shape
    idx = np.linspace(0, f - 1, min(frames, f)).round().astype(int)
    out = np.full((len(clips) * (h + gap) - gap, len(idx) * (w + gap) - gap, 3), 255, np.uint8)
    for r, clip in enumerate(clips):
        for c, i in enumerate(idx):
            out[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = clip[i]
    try:
        from PIL import Image, ImageDraw
    except ImportError:  # pragma: no cover
        return out
    im = Image.fromarray(out)
    draw = ImageDraw.Draw(im)
    for r, label in enumerate(labels):
        y = r * (h + gap) + 2
        draw.rectangle([0, y, 6 * len(label) + 4, y + 12], fill=(0, 0, 0))
        draw.text((2, y), label, fill=(255, 255, 255))
    return np.asarray(im)
