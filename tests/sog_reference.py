"""An independent NumPy decoder and encoder for PlayCanvas SOG, written from splat-transform's
`read-sog.ts`, `read-sog-v1.ts` and `write-sog.ts`. WebP goes through Pillow (libwebp), not the
Rust `image-webp` decoder morphgs uses, so agreement checks both the maths and the codec."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image

SQRT2 = np.sqrt(2.0)
QUAT_IDX = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]


def _rgba(data: bytes) -> np.ndarray:
    img = Image.open(io.BytesIO(data))
    return np.asarray(img.convert("RGBA")).reshape(-1, 4).astype(np.int64)


def _inv_log(v: np.ndarray) -> np.ndarray:
    return np.sign(v) * (np.exp(np.abs(v)) - 1.0)


def _logit(a: np.ndarray) -> np.ndarray:
    a = np.clip(a, 1e-6, 1 - 1e-6)
    return np.log(a / (1 - a))


def decode(load: Callable[[str], bytes]) -> dict[str, np.ndarray]:
    """Decode a SOG whose files `load(name)` returns. Returns float64 arrays in morphgs' layout."""
    meta = json.loads(load("meta.json"))
    v2 = meta.get("version") == 2
    n = meta["count"] if v2 else meta["means"]["shape"][0]
    lo = _rgba(load(meta["means"]["files"][0]))[:n]
    hi = _rgba(load(meta["means"]["files"][1]))[:n]
    q16 = (lo[:, :3] | (hi[:, :3] << 8)).astype(np.float64)
    mins, maxs = np.array(meta["means"]["mins"]), np.array(meta["means"]["maxs"])
    span = np.where(maxs - mins == 0, 1.0, maxs - mins)
    means = _inv_log(mins + span * q16 / 65535.0)

    qt = _rgba(load(meta["quats"]["files"][0]))[:n]
    quats = np.zeros((n, 4))
    for i, px in enumerate(qt):
        if not 252 <= px[3] <= 255:
            quats[i] = [1, 0, 0, 0]
            continue
        m = px[3] - 252
        comps = (px[:3] / 255.0 * 2 - 1) / SQRT2
        quats[i, QUAT_IDX[m]] = comps
        quats[i, m] = np.sqrt(max(0.0, 1 - np.sum(comps**2)))

    sc = _rgba(load(meta["scales"]["files"][0]))[:n]
    c0 = _rgba(load(meta["sh0"]["files"][0]))[:n]
    if v2:
        scb, ccb = np.array(meta["scales"]["codebook"]), np.array(meta["sh0"]["codebook"])
        log_scales = scb[sc[:, :3]]
        sh0 = ccb[c0[:, :3]]
        opacity = _logit(c0[:, 3] / 255.0)
    else:
        smin, smax = np.array(meta["scales"]["mins"]), np.array(meta["scales"]["maxs"])
        log_scales = smin + (smax - smin) * sc[:, :3] / 255.0
        cmin, cmax = np.array(meta["sh0"]["mins"]), np.array(meta["sh0"]["maxs"])
        sh0 = cmin[:3] + (cmax[:3] - cmin[:3]) * c0[:, :3] / 255.0
        opacity = cmin[3] + (cmax[3] - cmin[3]) * c0[:, 3] / 255.0

    out = {"means": means, "quats": quats, "log_scales": log_scales, "sh0": sh0,
           "opacity_logits": opacity}
    if "shN" in meta:
        cen_img = Image.open(io.BytesIO(load(meta["shN"]["files"][0])))
        cw = cen_img.width
        cen = _rgba(load(meta["shN"]["files"][0]))
        labels = _rgba(load(meta["shN"]["files"][1]))[:n]
        label = labels[:, 0] | (labels[:, 1] << 8)
        if v2:
            coeffs = [0, 3, 8, 15][meta["shN"]["bands"]]
            cb = np.array(meta["shN"]["codebook"])
            deq = lambda b: cb[b]  # noqa: E731
            count = meta["shN"]["count"]
        else:
            coeffs = {192: 3, 512: 8, 960: 15}[cw]
            lo_, hi_ = meta["shN"]["mins"], meta["shN"]["maxs"]
            deq = lambda b: lo_ + (hi_ - lo_) * b / 255.0  # noqa: E731
            count = cw // coeffs * cen_img.height
        rest = np.zeros((n, coeffs, 3))
        for j in range(coeffs):
            x = (label % 64) * coeffs + j
            y = label // 64
            ok = label < count
            px = cen[np.where(ok, y * cw + x, 0)]
            rest[:, j, :] = np.where(ok[:, None], deq(px[:, :3]), 0.0)
        out["sh_rest"] = rest
    return out


def zip_loader(path: Path) -> Callable[[str], bytes]:
    z = zipfile.ZipFile(path)
    return lambda name: z.read(name)


def dir_loader(path: Path) -> Callable[[str], bytes]:
    return lambda name: (path / name).read_bytes()


def _webp(texels: np.ndarray, width: int) -> bytes:
    h = -(-len(texels) // width)
    img = np.zeros((h * width, 4), np.uint8)
    img[: len(texels)] = texels
    buf = io.BytesIO()
    Image.fromarray(img.reshape(h, width, 4), "RGBA").save(buf, "WEBP", lossless=True,
                                                               exact=True)
    return buf.getvalue()


def encode_v1(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, sh0: np.ndarray,
              opacity: np.ndarray, width: int = 8) -> dict[str, bytes]:
    """A legacy (v1) SOG of a degree-0 scene, as the pre-codebook splat-transform wrote it."""
    n = len(means)

    def log_t(v: np.ndarray) -> np.ndarray:
        return np.sign(v) * np.log(np.abs(v) + 1)

    lt = log_t(means)
    mins, maxs = lt.min(0), lt.max(0)
    q = np.round(65535 * (lt - mins) / (maxs - mins)).astype(np.int64)
    lo = np.c_[q & 0xFF, np.full((n, 1), 255)].astype(np.uint8)
    hi = np.c_[q >> 8, np.full((n, 1), 255)].astype(np.uint8)
    qn = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    qt = np.zeros((n, 4), np.uint8)
    for i in range(n):
        m = int(np.argmax(np.abs(qn[i])))
        v = qn[i] * (np.sign(qn[i, m]) * SQRT2)
        qt[i, :3] = np.round(255 * (v[QUAT_IDX[m]] * 0.5 + 0.5))
        qt[i, 3] = 252 + m

    def lin(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo_, hi_ = v.min(0), v.max(0)
        return np.round(255 * (v - lo_) / (hi_ - lo_)).astype(np.uint8), lo_, hi_

    sq, smin, smax = lin(log_scales)
    c = np.c_[sh0, opacity]
    cq, cmin, cmax = lin(c)
    meta = {
        "means": {"shape": [n, 3], "dtype": "float32", "mins": mins.tolist(),
                  "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"shape": [n, 3], "dtype": "float32", "mins": smin.tolist(),
                   "maxs": smax.tolist(), "files": ["scales.webp"]},
        "quats": {"shape": [n, 4], "dtype": "uint8", "encoding": "quaternion_packed",
                  "files": ["quats.webp"]},
        "sh0": {"shape": [n, 1, 4], "dtype": "float32", "mins": cmin.tolist(),
                "maxs": cmax.tolist(), "files": ["sh0.webp"]},
    }
    return {
        "meta.json": json.dumps(meta).encode(),
        "means_l.webp": _webp(lo, width),
        "means_u.webp": _webp(hi, width),
        "quats.webp": _webp(qt, width),
        "scales.webp": _webp(np.c_[sq, np.full((n, 1), 255, np.uint8)], width),
        "sh0.webp": _webp(cq, width),
    }
