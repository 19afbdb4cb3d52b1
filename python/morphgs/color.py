"""Colour correction after refinement: Reinhard transfer in CIELAB (the paper, SPEC §5).

A refiner can shift a clip's colours; the paper matches them back to reference frames with
Reinhard et al.'s statistics transfer (2001, eq. 11) done in CIELAB rather than their lαβ space:
per channel, ``out = (x - mean_x) * std_ref / std_x + mean_ref``, the means and standard deviations
taken over **every pixel of every frame** of the clip (one transform for the whole clip, so the
correction does not flicker from frame to frame).

Conventions: RGB is sRGB (IEC 61966-2-1 transfer curve) in [0, 1], or uint8; Lab is CIE 1976
L*a*b* with the D65 white of the 2-degree observer (0.95047, 1, 1.08883), L in [0, 100], with the exact CIE
constants (6/29)^3 and 1/(3 (6/29)^2) at the knee of the cube root (scikit-image's ``rgb2lab``
rounds them to 0.008856 and 7.787; values near the knee differ by ~1e-4). Results are clipped to [0, 1] after the transfer.

NumPy only (no torch): evaluation and the CLI use it too. float32 and uint8 clips are converted in
float32 (statistics are summed in float64), float64 clips in float64; a few frames at a time.
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


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


_U8_TO_LINEAR = _srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)


def _as_float(rgb: np.ndarray) -> np.ndarray:
    """float64 stays float64; uint8 (/ 255) and other floats become float32."""
    a = np.asarray(rgb)
    if a.shape[-1:] != (3,):
        raise ValueError(f"colours must have 3 channels last, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float32) * np.float32(1.0 / 255.0)
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"colours must be uint8 or float in [0, 1], got {a.dtype}")
    return a if a.dtype == np.float64 else a.astype(np.float32, copy=False)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] (or uint8), channels last, to CIELAB (D65, 2 degrees), float64.

    Args:
        rgb: (..., 3) array.

    Returns:
        (..., 3) array of L, a, b: float64 for float64 input, else float32.
    """
    raw = np.asarray(rgb)
    if raw.dtype == np.uint8 and raw.shape[-1:] == (3,):
        lin = _U8_TO_LINEAR[raw]  # the transfer curve of the 256 values, once
    else:
        c = _as_float(raw)
        t = c.dtype.type
        lin = np.where(c <= t(0.04045), c / t(12.92), ((np.maximum(c, t(0.04045)) + t(0.055)) / t(1.055)) ** t(2.4))
    t = lin.dtype.type
    xyz = (lin @ (_RGB2XYZ.T / _WHITE).astype(lin.dtype))
    f = np.where(xyz > t(_DELTA**3), np.cbrt(xyz), xyz / t(3 * _DELTA**2) + t(4.0 / 29.0))
    out = np.empty_like(f)
    out[..., 0] = t(116.0) * f[..., 1] - t(16.0)
    out[..., 1] = t(500.0) * (f[..., 0] - f[..., 1])
    out[..., 2] = t(200.0) * (f[..., 1] - f[..., 2])
    return out


def lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    """CIELAB (D65, 2 degrees) to sRGB, float64, **not** clipped (out-of-gamut values stay).

    Args:
        lab: (..., 3) array of L, a, b.

    Returns:
        (..., 3) sRGB: float32 for float32 input, else float64.
    """
    lab = np.asarray(lab)
    if lab.dtype != np.float32:
        lab = lab.astype(np.float64)
    t = lab.dtype.type
    f = np.empty_like(lab)
    f[..., 1] = (lab[..., 0] + t(16.0)) / t(116.0)
    f[..., 0] = f[..., 1] + lab[..., 1] / t(500.0)
    f[..., 2] = f[..., 1] - lab[..., 2] / t(200.0)
    xyz = np.where(f > t(_DELTA), f * f * f, t(3 * _DELTA**2) * (f - t(4.0 / 29.0)))
    lin = xyz @ (_XYZ2RGB.T * _WHITE[:, None]).astype(lab.dtype)
    return np.where(lin <= t(0.0031308), t(12.92) * lin,
                    t(1.055) * np.abs(lin) ** t(1 / 2.4) * np.sign(lin) - t(0.055))


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
    acc = _Moments()
    for chunk in _chunks(frames):
        acc.add(rgb_to_lab(chunk))
    return acc.result()


class _Moments:
    """Per-channel count, sum and sum of squares (float64) over chunks of Lab pixels."""

    def __init__(self) -> None:
        self.n = 0
        self.s = np.zeros(3)
        self.s2 = np.zeros(3)

    def add(self, lab: np.ndarray) -> None:
        flat = lab.reshape(-1, 3)
        self.n += flat.shape[0]
        self.s += flat.sum(axis=0, dtype=np.float64)
        self.s2 += np.einsum("ij,ij->j", flat, flat, dtype=np.float64)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        mean = self.s / self.n
        return mean, np.sqrt(np.maximum(self.s2 / self.n - mean * mean, 0.0))


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
    labs = []  # the clip's Lab (float32 for float32/uint8 clips), kept for the transform pass
    acc = _Moments()
    for chunk in _chunks(src):
        labs.append(rgb_to_lab(chunk))
        acc.add(labs[-1])
    mean_x, std_x = acc.result()
    mean_r, std_r = lab_stats(reference)
    gain = std_r / np.maximum(std_x, eps)
    out = np.empty(src.shape, np.float32)
    flat = out.reshape((-1,) + src.shape[-3:]) if src.ndim == 4 else out[None]
    i = 0
    for lab in labs:
        t = lab.dtype.type
        lab *= gain.astype(lab.dtype)
        lab += (mean_r - mean_x * gain).astype(lab.dtype)
        flat[i:i + len(lab)] = np.clip(lab_to_rgb(lab), t(0.0), t(1.0))
        i += len(lab)
    return out
