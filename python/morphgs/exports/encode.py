"""Clips of a pair as MP4 files, encoded in parallel.

Each MP4 is one ffmpeg process (`morphgs.media.encode_frames`: ffmpeg reads the PNGs itself, one
encoder thread), so threads of this process run several encodes at once without holding the GIL.
One encoder thread per clip keeps the bytes independent of how many run at once; parallelism comes
from running clips side by side (both sides of a pair, several pairs).
"""

from __future__ import annotations

import shutil
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

from morphgs import media
from morphgs.exports.source import PairEntry

__all__ = ["clip_to_mp4", "default_workers", "ordered_map", "reference_png"]

T = TypeVar("T")
R = TypeVar("R")


def default_workers() -> int:
    """Concurrent encodes: the native thread count (`RAYON_NUM_THREADS` / `MORPHGS_NUM_THREADS`)."""
    from morphgs import _core

    return max(1, int(_core.num_threads()))


def clip_to_mp4(entry: PairEntry, side: str, dst: Path, *, fps: float, crf: int) -> Path:
    """Write the `side` ("clean" or "corrupted") clip of a pair as an MP4 at `dst`.

    Frame folders are encoded (H.264, `media.encode_frames`); pairs curated with --video are copied
    byte for byte (no second lossy encode; their frame rate is the one curate used).
    """
    src = entry.clean if side == "clean" else entry.corrupted
    dst.parent.mkdir(parents=True, exist_ok=True)
    if entry.video:
        shutil.copyfile(src, dst)
        return dst
    return media.encode_frames(src, dst, fps=fps, crf=crf)


def reference_png(entry: PairEntry, index: int, dst: Path) -> Path:
    """Write clean frame `index` of a pair as a PNG at `dst` (copied from a frame folder, or decoded
    from a clean MP4)."""
    if not 0 <= index < entry.frames:
        from morphgs.exports.source import ExportError

        raise ExportError(f"reference frame {index} asked for, pair {entry.pair_id} has {entry.frames} frames")
    dst.parent.mkdir(parents=True, exist_ok=True)
    if not entry.video:
        shutil.copyfile(entry.frame_path("clean", index), dst)
        return dst
    from PIL import Image

    frame = media.read_clip(entry.clean, start=index, count=1)[0]
    Image.fromarray(frame).save(dst, format="PNG")
    return dst


def ordered_map(fn: Callable[[T], R], items: Iterable[T], *, workers: int, window: int | None = None) -> Iterator[R]:
    """`map(fn, items)` on a thread pool: results in input order, at most `window` (2 x workers) in
    flight, so a long export holds a bounded number of finished results in memory. An exception in
    `fn` is raised here once its turn comes; pending work is cancelled."""
    if workers <= 1:
        yield from map(fn, items)
        return
    window = window or 2 * workers
    pending: deque[Future[R]] = deque()
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="morphgs-export") as pool:
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) >= window:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()
