"""Per-pair statistics of a corrupted/clean clip pair: small pure functions on float clips.

Clips are arrays (F, H, W, 3) in [0, 1] (uint8 / 255 or renders), corrupted first, clean second.
The statistics describe *how* a pair is corrupted, not only how much: blur, noise and holes put
their error in different frequency bands, floaters change frame to frame, a colour cast moves
the mean colour. They are what calibration matches (PSNR) and what the goodness of fit compares
(all of them, docs/calibration.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BANDS", "BAND_EDGES", "SPECTRUM_NAMES", "STAT_NAMES", "color_shift", "coverage", "error_spectrum", "frame_lpips", "frame_psnr",
           "frame_ssim", "pair_stats", "temporal_error"]

#: Edges of the log-frequency bands of `error_spectrum`, in cycles per pixel (radial frequency).
BAND_EDGES: tuple[float, ...] = (1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 0.7072)
#: The number of bands of `error_spectrum`.
BANDS = len(BAND_EDGES) - 1
#: The band statistics of `pair_stats`, lowest frequency first.
SPECTRUM_NAMES: tuple[str, ...] = tuple(f"spectrum_{k}" for k in range(BANDS))


def _check(corrupted: np.ndarray, clean: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(corrupted, dtype=np.float32)
    b = np.asarray(clean, dtype=np.float32)
    if a.shape != b.shape or a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"pair clips must both be (F, H, W, 3) of the same size, got {a.shape} and {b.shape}")
    return a, b


def frame_psnr(corrupted: np.ndarray, clean: np.ndarray) -> np.ndarray:
    """PSNR per frame (dB, data range 1; capped at 100 dB for identical frames)."""
    a, b = _check(corrupted, clean)
    mse = ((a.astype(np.float64) - b) ** 2).mean(axis=(1, 2, 3))
    return np.minimum(10.0 * np.log10(1.0 / np.maximum(mse, 1e-10)), 100.0)  # type: ignore[no-any-return]


def frame_ssim(corrupted: np.ndarray, clean: np.ndarray) -> np.ndarray:
    """SSIM per frame (torchmetrics' definition, `morphgs.metrics.ssim`)."""
    from morphgs.metrics import ssim

    a, b = _check(corrupted, clean)
    return np.asarray(ssim(a, b, reduction="none"), dtype=np.float64)


def frame_lpips(corrupted: np.ndarray, clean: np.ndarray) -> np.ndarray | None:
    """LPIPS (AlexNet) per frame, or None where torch or the weights are not installed."""
    try:
        from morphgs.metrics import LPIPSWeightsError, lpips
    except ImportError:  # pragma: no cover - metrics extra missing
        return None
    a, b = _check(corrupted, clean)
    try:
        return np.asarray(lpips(a, b, reduction="none"), dtype=np.float64)
    except (ImportError, LPIPSWeightsError):
        return None


def error_spectrum(corrupted: np.ndarray, clean: np.ndarray, edges: tuple[float, ...] = BAND_EDGES) -> np.ndarray:
    """Error-to-signal power ratio per log-frequency band, in dB: shape (len(edges) - 1,).

    For each band [f_k, f_k+1) of radial frequency (cycles per pixel), 10 log10 of the power of
    the error (corrupted - clean) over the power of the clean signal, both summed over frames and
    the luminance (channel mean), means removed. Blur puts its error at high frequencies (ratio
    near 0 dB there, far below at low ones), white noise is flat in error power, holes and
    floaters raise the low bands.
    """
    a, b = _check(corrupted, clean)
    err = (a - b).mean(axis=-1).astype(np.float64)
    sig = b.mean(axis=-1).astype(np.float64)
    err -= err.mean(axis=(1, 2), keepdims=True)
    sig -= sig.mean(axis=(1, 2), keepdims=True)
    pe = (np.abs(np.fft.rfft2(err)) ** 2).sum(axis=0)
    ps = (np.abs(np.fft.rfft2(sig)) ** 2).sum(axis=0)
    h, w = err.shape[1:]
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    r = np.sqrt(fx**2 + fy**2)
    out = np.empty(len(edges) - 1)
    for k in range(len(edges) - 1):
        band = (r >= edges[k]) & (r < edges[k + 1])
        e, s = pe[band].sum(), ps[band].sum()
        out[k] = 10.0 * np.log10(max(e, 1e-12) / max(s, 1e-12)) if band.any() else np.nan
    return out


def color_shift(corrupted: np.ndarray, clean: np.ndarray) -> float:
    """Mean over frames of Delta E*ab between the frames' mean CIELAB colours
    (`morphgs.metrics.color_shift`)."""
    from morphgs.metrics import color_shift as _cs

    a, b = _check(corrupted, clean)
    return float(_cs(a, b, reduction="mean"))


def coverage(corrupted: np.ndarray, clean: np.ndarray, *, corrupted_alpha: np.ndarray | None = None,
             clean_alpha: np.ndarray | None = None, background: float = 2.0 / 255.0) -> float:
    """How much of the clean image's content the corrupted frames still cover, in [0, 1+].

    With alphas: sum(corrupted alpha) / sum(clean alpha). Without (pairs read from disk): the
    share of clean foreground pixels (any channel above `background`) that are foreground in the
    corrupted frames too, so holes (pruned or missing parts on a black background) lower it.
    """
    a, b = _check(corrupted, clean)
    if corrupted_alpha is not None and clean_alpha is not None:
        return float(np.sum(corrupted_alpha, dtype=np.float64) / max(np.sum(clean_alpha, dtype=np.float64), 1e-12))
    fg_clean = b.max(axis=-1) > background
    fg_both = fg_clean & (a.max(axis=-1) > background)
    return float(fg_both.sum() / max(int(fg_clean.sum()), 1))


def temporal_error(corrupted: np.ndarray, clean: np.ndarray) -> float:
    """RMS frame-to-frame change of the error, sqrt(mean((e_t+1 - e_t)^2)) with e = corrupted -
    clean: 0 for a static error (a colour cast), large for flickering floaters. NaN for one frame."""
    a, b = _check(corrupted, clean)
    if len(a) < 2:
        return float("nan")
    e = a.astype(np.float64) - b
    return float(np.sqrt(np.mean((e[1:] - e[:-1]) ** 2)))


#: The scalar statistics of `pair_stats` (besides the per-frame arrays), in report order.
STAT_NAMES: tuple[str, ...] = ("psnr", "ssim", "lpips", "color_shift", "coverage", "temporal_error", *SPECTRUM_NAMES)


def pair_stats(corrupted: np.ndarray, clean: np.ndarray, *, lpips: bool = False, **coverage_args: Any) -> dict[str, Any]:
    """Every statistic of one pair: {"frame_psnr": [...], "frame_ssim": [...], "frame_lpips":
    [...] | None, and the scalars of `STAT_NAMES` (psnr / ssim / lpips are the frame medians;
    lpips is None unless asked and available; spectrum_k the bands of `error_spectrum`)}."""
    p = frame_psnr(corrupted, clean)
    s = frame_ssim(corrupted, clean)
    lp = frame_lpips(corrupted, clean) if lpips else None
    spec = error_spectrum(corrupted, clean)
    out: dict[str, Any] = {
        "frame_psnr": [float(v) for v in p], "frame_ssim": [float(v) for v in s],
        "frame_lpips": None if lp is None else [float(v) for v in lp],
        "psnr": float(np.median(p)), "ssim": float(np.median(s)),
        "lpips": None if lp is None else float(np.median(lp)),
        "color_shift": color_shift(corrupted, clean), "coverage": coverage(corrupted, clean, **coverage_args),
        "temporal_error": temporal_error(corrupted, clean),
    }
    out.update({name: float(v) for name, v in zip(SPECTRUM_NAMES, spec, strict=True)})
    return out
