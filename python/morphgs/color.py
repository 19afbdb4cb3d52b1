"""Colour correction after refinement: Reinhard transfer in CIELAB (the paper, SPEC §5).

A refiner can shift a clip's colours; the paper matches them back to reference frames with
Reinhard et al.'s statistics transfer (2001, eq. 11) done in CIELAB rather than their lαβ space:
per channel, ``out = (x - mean_x) * std_ref / std_x + mean_ref``, the means and standard deviations
taken over **every pixel of every frame** of the clip (one transform for the whole clip, so the
correction does not flicker from frame to frame).

Conventions: RGB is sRGB (IEC 61966-2-1 transfer curve) in [0, 1], or uint8; Lab is CIE 1976
L*a*b* with the D65 white of the 2-degree observer (0.95047, 1, 1.08883), L in [0, 100] — the
values scikit-image's ``rgb2lab`` gives. Results are clipped to [0, 1] after the transfer.

NumPy only (no torch): evaluation and the CLI use it too. Frames are converted a few at a time so
a 49-frame 832x480 clip needs a few hundred MB at most.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

__all__ = ["lab_stats", "lab_to_rgb", "reinhard_transfer", "rgb_to_lab"]

# sRGB (linear) -> XYZ, D65
_RGB2XYZ = np.array([[0.412453, 0.357580, 0.180423],
                     [0.212671, 0.715160, 0.072169],
                     [0.019334, 0.119193, 0.950227]])
_XYZ2RGB = np.linalg.inv(_RGB2XYZ)
_WHITE = np.array([0.95047, 1.0, 1.08883])
_DELTA = 6.0 / 29.0
_CHUNK = 4  # frames converted at a time


def _as_float(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.shape[-1:] != (3,):
        raise ValueError(f"colours must have 3 channels last, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float64) / 255.0
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"colours must be uint8 or float in [0, 1], got {a.dtype}")
    return a.astype(np.float64)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] (or uint8), channels last, to CIELAB (D65, 2 degrees), float64.

    Args:
        rgb: (..., 3) array.

    Returns:
        (..., 3) float64 array of L, a, b.
    """
    c = _as_float(rgb)
    lin = np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)
    xyz = (lin @ _RGB2XYZ.T) / _WHITE
    f = np.where(xyz > _DELTA**3, np.cbrt(xyz), xyz / (3 * _DELTA**2) + 4.0 / 29.0)
    L = 116.0 * f[..., 1] - 16.0
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return np.stack([L, a, b], axis=-1)


def lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    """CIELAB (D65, 2 degrees) to sRGB, float64, **not** clipped (out-of-gamut values stay).

    Args:
        lab: (..., 3) array of L, a, b.

    Returns:
        (..., 3) float64 sRGB.
    """
    lab = np.asarray(lab, dtype=np.float64)
    fy = (lab[..., 0] + 16.0) / 116.0
    f = np.stack([fy + lab[..., 1] / 500.0, fy, fy - lab[..., 2] / 200.0], axis=-1)
    xyz = np.where(f > _DELTA, f**3, 3 * _DELTA**2 * (f - 4.0 / 29.0)) * _WHITE
    lin = xyz @ _XYZ2RGB.T
    return np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.abs(lin) ** (1 / 2.4) * np.sign(lin) - 0.055)


def _chunks(frames: np.ndarray) -> Iterator[np.ndarray]:
    a = np.asarray(frames)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4 or a.shape[-1] != 3 or a.shape[0] == 0:
        raise ValueError(f"a clip must be (F, H, W, 3) or (H, W, 3) with F >= 1, got shape {a.shape}")
    for i in range(0, a.shape[0], _CHUNK):
        yield a[i:i + _CHUNK]


def lab_stats(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and standard deviation of a clip in CIELAB, over all its pixels.

    Args:
        frames: (F, H, W, 3) or (H, W, 3), uint8 or float sRGB in [0, 1].

    Returns:
        (mean, std): two float64 arrays of 3 values (L, a, b).
    """
    n = 0
    s = np.zeros(3)
    s2 = np.zeros(3)
    for chunk in _chunks(frames):
        lab = rgb_to_lab(chunk).reshape(-1, 3)
        n += lab.shape[0]
        s += lab.sum(axis=0)
        s2 += (lab * lab).sum(axis=0)
    mean = s / n
    var = np.maximum(s2 / n - mean * mean, 0.0)
    return mean, np.sqrt(var)


def reinhard_transfer(frames: np.ndarray, reference: np.ndarray, *, eps: float = 1e-6) -> np.ndarray:
    """Match a clip's colour statistics to reference frames (Reinhard transfer in CIELAB).

    Per Lab channel, ``out = (x - mean_x) * std_ref / max(std_x, eps) + mean_ref``, with the
    statistics of each side taken over all its frames at once, then back to sRGB and clipped.

    Args:
        frames: the clip to correct, (F, H, W, 3) or (H, W, 3), uint8 or float in [0, 1].
        reference: frames with the wanted colours (any count and size), same conventions.
        eps: floor of the clip's standard deviation (a flat channel is shifted, not blown up).

    Returns:
        float32 array shaped like `frames`, in [0, 1].

    Raises:
        ValueError: shapes that are not clips of RGB frames.
    """
    src = np.asarray(frames)
    mean_x, std_x = lab_stats(src)
    mean_r, std_r = lab_stats(reference)
    gain = std_r / np.maximum(std_x, eps)
    out = np.empty(src.shape, np.float32)
    flat = out.reshape((-1,) + src.shape[-3:]) if src.ndim == 4 else out[None]
    i = 0
    for chunk in _chunks(src):
        lab = (rgb_to_lab(chunk) - mean_x) * gain + mean_r
        flat[i:i + len(chunk)] = np.clip(lab_to_rgb(lab), 0.0, 1.0)
        i += len(chunk)
    return out
