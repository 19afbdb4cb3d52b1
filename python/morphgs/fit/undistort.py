"""Undistortion of photos for `morphgs fit` (docs/fit.md, "Real captures").

The fit renders ideal pinhole cameras, so photos taken through a lens with radial / tangential
distortion are remapped to pinhole images first, as gsplat's COLMAP parser does with OpenCV:
`cv2.getOptimalNewCameraMatrix(K, D, size, alpha=0)` gives the new pinhole intrinsics and the
region of interest where every pixel has a source pixel, `cv2.initUndistortRectifyMap` +
`cv2.remap` (bilinear for images, nearest for masks) resample, and the result is cropped to that
region (the principal point moves with the crop). The one difference from gsplat: OpenCV puts
the top-left pixel's centre at (0, 0), COLMAP and morphgs at (0.5, 0.5), so the principal point
is shifted by half a pixel into OpenCV's convention and back.

Supported: COLMAP SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV (and the pinhole models, untouched);
a transforms.json's k1 k2 k3 p1 p2 with a perspective camera_model. Fisheye models are refused
with an error that says how to undistort them first (`colmap image_undistorter`).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.camera import Camera
from morphgs.trajectory import CaptureError

__all__ = ["Distortion", "colmap_distortion", "transforms_distortion", "undistort", "undistorted_camera"]

FISHEYE_MODELS = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE",
                  "RAD_TAN_THIN_PRISM_FISHEYE", "FOV", "FISHEYE", "EQUIRECTANGULAR", "EQUIRECT")
_HOW = ("undistort the capture first (colmap image_undistorter, or ns-process-data with "
        "--camera-type perspective) and fit its pinhole output")


@dataclass(frozen=True)
class Distortion:
    """OpenCV distortion coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]) of a perspective camera,
    with the camera model they came from (for messages and the cache key)."""

    model: str
    coeffs: tuple[float, ...]


def colmap_distortion(model: str, params: tuple[float, ...], where: str) -> Distortion | None:
    """The distortion of a COLMAP camera (None for SIMPLE_PINHOLE / PINHOLE or all-zero
    coefficients); CaptureError for fisheye models."""
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return None
    if model == "SIMPLE_RADIAL":
        d: tuple[float, ...] = (params[3], 0.0, 0.0, 0.0)
    elif model == "RADIAL":
        d = (params[3], params[4], 0.0, 0.0)
    elif model == "OPENCV":
        d = tuple(params[4:8])
    elif model == "FULL_OPENCV":
        d = tuple(params[4:12])  # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's rational model, same order
    elif model in FISHEYE_MODELS:
        raise CaptureError(f"{where}: camera model {model} is a fisheye model, which morphgs fit does not "
                           f"undistort; {_HOW}")
    else:
        raise CaptureError(f"{where}: camera model {model} is not supported by morphgs fit; {_HOW}")
    return Distortion(model, tuple(float(v) for v in d)) if any(v != 0.0 for v in d) else None


def transforms_distortion(model: str, dist: dict[str, float], where: str) -> Distortion | None:
    """The distortion of a transforms.json frame (camera_model + k1 k2 k3 k4 p1 p2)."""
    if model in FISHEYE_MODELS:
        if any(v != 0.0 for v in dist.values()):
            raise CaptureError(f"{where}: camera_model {model} is a fisheye model, which morphgs fit does not "
                               f"undistort; {_HOW}")
        raise CaptureError(f"{where}: camera_model {model} is not a perspective camera; {_HOW}")
    if model not in ("OPENCV", "PERSPECTIVE", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        raise CaptureError(f"{where}: camera_model {model!r} is not supported (OPENCV / PINHOLE perspective "
                           f"cameras are); {_HOW}")
    if dist.get("k4", 0.0) != 0.0:
        raise CaptureError(f"{where}: k4 = {dist['k4']} in a perspective camera (nerfstudio's r^8 term) has no "
                           f"OpenCV equivalent; {_HOW}")
    d: tuple[float, ...] = (dist.get("k1", 0.0), dist.get("k2", 0.0), dist.get("p1", 0.0), dist.get("p2", 0.0),
                            dist.get("k3", 0.0))
    if d[4] == 0.0:
        d = d[:4]
    return Distortion(model, tuple(float(v) for v in d)) if any(v != 0.0 for v in d) else None


def _cv2() -> Any:
    try:
        import cv2
    except ImportError:
        raise CaptureError("undistorting photos needs OpenCV: pip install 'morphgs[fit]' "
                           "(opencv-python-headless)") from None
    return cv2


def _k_cv(cam: Camera) -> np.ndarray:
    k = cam.K.copy()
    k[0, 2] -= 0.5  # morphgs / COLMAP pixel centres at +0.5, OpenCV's at 0
    k[1, 2] -= 0.5
    return k


def _new_matrix(cam: Camera, dist: Distortion, where: str) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    cv2 = _cv2()
    k_new, roi = cv2.getOptimalNewCameraMatrix(_k_cv(cam), np.asarray(dist.coeffs, np.float64),
                                               (cam.width, cam.height), 0)
    x, y, w, h = (int(v) for v in roi)
    if w < 2 or h < 2:
        raise CaptureError(f"{where}: the {dist.model} distortion {list(dist.coeffs)} leaves no valid region "
                           f"after undistortion ({w}x{h}); check the camera's coefficients")
    return np.asarray(k_new, np.float64), (x, y, w, h)


def undistorted_camera(cam: Camera, dist: Distortion, where: str = "camera") -> Camera:
    """The pinhole camera of the undistorted, cropped image of `cam` (no pixels read)."""
    k_new, (x, y, w, h) = _new_matrix(cam, dist, where)
    return Camera(k_new[0, 0], k_new[1, 1], k_new[0, 2] + 0.5 - x, k_new[1, 2] + 0.5 - y, w, h,
                  cam.world_to_camera, cam.near, cam.far)


def cache_name(path: Path, cam: Camera, dist: Distortion, kind: str) -> str:
    """A file name for the undistorted `kind` ("image" / "mask") of `path` that changes with the
    camera and the coefficients (so a changed model never reuses a stale file)."""
    key = repr((str(path), kind, cam.width, cam.height, cam.K.tolist(), dist.model, dist.coeffs))
    return f"{path.stem}-{kind}-{hashlib.sha256(key.encode()).hexdigest()[:12]}.png"


def undistort(img: np.ndarray, cam: Camera, dist: Distortion, *, nearest: bool = False,
              where: str = "camera") -> tuple[np.ndarray, Camera]:
    """(undistorted and cropped image, its pinhole camera). `img` is (H, W) or (H, W, 3) at the
    camera's size."""
    cv2 = _cv2()
    k_new, (x, y, w, h) = _new_matrix(cam, dist, where)
    mx, my = cv2.initUndistortRectifyMap(_k_cv(cam), np.asarray(dist.coeffs, np.float64), None, k_new,
                                         (cam.width, cam.height), cv2.CV_32FC1)
    out = cv2.remap(np.ascontiguousarray(img), mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT)
    out = np.ascontiguousarray(out[y:y + h, x:x + w])
    return out, undistorted_camera(cam, dist, where)


def cached_undistort(img_path: Path, read: Any, cam: Camera, dist: Distortion, cache: Path | None, *,
                     nearest: bool = False, kind: str = "image") -> tuple[np.ndarray, Camera]:
    """`undistort` of the image `read()` returns, through a PNG cache in `cache` (the run
    folder's `undistorted/`; None: no cache). Cached files are written atomically."""
    from morphgs._core import _write_png
    from morphgs.media import read_image

    where = str(img_path)
    if cache is not None:
        target = cache / cache_name(img_path, cam, dist, kind)
        if target.is_file():
            out = read_image(target)
            if kind == "mask":
                out = out[..., 0]
            return np.ascontiguousarray(out), undistorted_camera(cam, dist, where)
    out, ucam = undistort(read(), cam, dist, nearest=nearest, where=where)
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.tmp{os.getpid()}.png")
        rgb = out if out.ndim == 3 else np.repeat(out[..., None], 3, axis=2)
        _write_png(tmp, np.ascontiguousarray(rgb.astype(np.uint8)))
        os.replace(tmp, target)
    return out, ucam
