"""Which part of a pair a sample is: F consecutive frames from a start frame, an optional resize,
a crop and an optional horizontal flip — chosen at random in training, centred in evaluation —
and what that does to the pinhole intrinsics (SPEC §3 conventions: pixel centres at +0.5).

Pure NumPy functions; the datasets apply them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Window", "adjust_intrinsics", "choose_window"]


@dataclass(frozen=True)
class Window:
    """Frames [start, start + frames) of a pair, resized to `resized` (H, W) when set, then the
    crop rows [y0, y0 + height) and columns [x0, x0 + width), then mirrored left-right if `flip`."""

    start: int
    frames: int
    y0: int
    x0: int
    height: int
    width: int
    flip: bool = False
    resized: tuple[int, int] | None = None


def choose_window(
    n_frames: int,
    frame_hw: tuple[int, int],
    *,
    frames: int,
    crop: tuple[int, int] | None,
    resize: tuple[int, int] | None = None,
    rng: np.random.Generator | None = None,
    flip: bool = False,
) -> Window:
    """Pick a window of a clip.

    Args:
        n_frames: frames in the clip; frame_hw: its (H, W).
        frames: F, consecutive frames to take.
        crop: (H, W) of the crop, or None for the whole (resized) frame.
        resize: (H, W) the frames are resized to before cropping, or None.
        rng: random start, crop and flip when given; centre start and crop (no flip) when None.
        flip: whether a random horizontal flip (probability 1/2) is allowed.

    Returns:
        Window.

    Raises:
        ValueError: a clip shorter than F, or a crop larger than the (resized) frame.
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if n_frames < frames:
        raise ValueError(f"clip of {n_frames} frames is shorter than the {frames} frames asked for")
    h, w = resize if resize is not None else frame_hw
    ch, cw = crop if crop is not None else (h, w)
    if ch > h or cw > w or ch < 1 or cw < 1:
        raise ValueError(f"crop {ch}x{cw} (HxW) does not fit frames of {h}x{w}")
    if rng is None:
        return Window((n_frames - frames) // 2, frames, (h - ch) // 2, (w - cw) // 2, ch, cw, False, resize)
    start = int(rng.integers(0, n_frames - frames + 1))
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    flipped = bool(flip and rng.integers(0, 2) == 1)
    return Window(start, frames, y0, x0, ch, cw, flipped, resize)


def adjust_intrinsics(K: np.ndarray, window: Window, frame_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics (..., 3, 3) of the original frames -> those of the windowed frames.

    Resizing scales fx, cx by W'/W and fy, cy by H'/H; cropping moves the principal point by the
    crop's corner; a left-right mirror maps u to width - u, i.e. fx' = -fx and cx' = width - cx
    (a mirrored camera: honest, but a negative focal length).
    """
    out = np.array(K, dtype=np.float64, copy=True)
    if window.resized is not None:
        sy = window.resized[0] / frame_hw[0]
        sx = window.resized[1] / frame_hw[1]
        out[..., 0, :] *= sx
        out[..., 1, :] *= sy
    out[..., 0, 2] -= window.x0
    out[..., 1, 2] -= window.y0
    if window.flip:
        out[..., 0, 0] *= -1.0
        out[..., 0, 1] *= -1.0
        out[..., 0, 2] = window.width - out[..., 0, 2]
    return out
