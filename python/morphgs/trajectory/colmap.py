"""COLMAP sparse models: `cameras` + `images` in text (.txt) or binary (.bin) form.

images store world-to-camera poses (p_c = R(q) p_w + t, q scalar first) in OpenCV axes, which is
the morphgs convention (SPEC §3), and COLMAP's principal point uses the same pixel-centre
convention (top-left pixel centre at (0.5, 0.5)): values are used as they are.
"""

from __future__ import annotations

import os
import struct
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from morphgs._core import MorphgsWarning
from morphgs.camera import Camera, Cameras
from morphgs.trajectory._common import CaptureError, check_resolution, stack_resized
from morphgs.trajectory._rotations import quat_to_matrix

__all__ = ["ColmapView", "from_colmap", "find_colmap_model", "read_colmap_views"]

# model id -> (name, number of params); COLMAP src/colmap/sensor/models.h
_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_BY_NAME = {name: (mid, n) for mid, (name, n) in _MODELS.items()}
# models whose first parameter is one shared focal length f (then cx, cy)
_SINGLE_F = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}
_FISHEYE = {"OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE",
            "RAD_TAN_THIN_PRISM_FISHEYE", "FOV"}

_Intr = tuple[str, int, int, tuple[float, ...]]


@dataclass(frozen=True)
class ColmapView:
    """One registered image of a COLMAP model: its name, its pinhole camera at the recorded size
    (fx, fy, cx, cy; the distortion parameters left out), the camera model and every parameter."""

    name: str
    camera: Camera
    model: str
    params: tuple[float, ...]
    camera_id: int


def _pinhole(model: str, params: Sequence[float]) -> tuple[float, float, float, float]:
    if model in _SINGLE_F:
        f, cx, cy = params[0], params[1], params[2]
        return f, f, cx, cy
    return params[0], params[1], params[2], params[3]


def _read_cameras_txt(path: Path) -> dict[int, _Intr]:
    cams: dict[int, _Intr] = {}
    for ln, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            cid, model, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = [float(v) for v in parts[4:]]
        except (IndexError, ValueError):
            raise CaptureError(f"{path}:{ln}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'") from None
        if model not in _BY_NAME:
            raise CaptureError(f"{path}:{ln}: unknown camera model {model!r}")
        if len(params) != _BY_NAME[model][1]:
            raise CaptureError(f"{path}:{ln}: model {model} takes {_BY_NAME[model][1]} params, got {len(params)}")
        cams[cid] = (model, w, h, tuple(params))
    return cams


def _read_images_txt(path: Path) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    out = []
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.lstrip().startswith("#")]
    # Each image takes two lines (pose, then its 2D points, which may be empty).
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if not line:
            i += 1
            continue
        parts = line.split()
        try:
            q = np.array([float(v) for v in parts[1:5]])
            t = np.array([float(v) for v in parts[5:8]])
            cid = int(parts[8])
            name = " ".join(parts[9:])
        except (IndexError, ValueError):
            raise CaptureError(f"{path}: bad image line {line[:80]!r} (expected "
                               "'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME')") from None
        if len(q) != 4 or len(t) != 3 or not name:
            raise CaptureError(f"{path}: bad image line {line[:80]!r}")
        out.append((name, cid, q, t))
        i += 2
    return out


def _read(f: BinaryIO, fmt: str, path: Path) -> tuple[object, ...]:
    size = struct.calcsize(fmt)
    b = f.read(size)
    if len(b) != size:
        raise CaptureError(f"{path}: file ends early")
    return struct.unpack(fmt, b)


def _read_cameras_bin(path: Path) -> dict[int, _Intr]:
    cams: dict[int, _Intr] = {}
    with open(path, "rb") as f:
        (n,) = _read(f, "<Q", path)
        for _ in range(int(n)):  # type: ignore[call-overload]
            cid, mid, w, h = _read(f, "<iiQQ", path)
            if mid not in _MODELS:
                raise CaptureError(f"{path}: unknown camera model id {mid}")
            model, npar = _MODELS[mid]  # type: ignore[index]
            params = _read(f, f"<{npar}d", path)
            cams[int(cid)] = (model, int(w), int(h), tuple(float(v) for v in params))  # type: ignore[arg-type, call-overload]
    return cams


def _read_images_bin(path: Path) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    out = []
    with open(path, "rb") as f:
        (n,) = _read(f, "<Q", path)
        for _ in range(int(n)):  # type: ignore[call-overload]
            vals = _read(f, "<i7di", path)
            q = np.array(vals[1:5], dtype=np.float64)
            t = np.array(vals[5:8], dtype=np.float64)
            cid = int(vals[8])  # type: ignore[call-overload]
            name = bytearray()
            while True:
                c = f.read(1)
                if not c:
                    raise CaptureError(f"{path}: file ends inside an image name")
                if c == b"\x00":
                    break
                name += c
            (npts,) = _read(f, "<Q", path)
            skip = 24 * int(npts)  # type: ignore[call-overload]
            if len(f.read(skip)) != skip:
                raise CaptureError(f"{path}: file ends inside the 2D points of {name.decode(errors='replace')}")
            out.append((name.decode("utf-8", errors="replace"), cid, q, t))
    return out


def find_colmap_model(folder: str | os.PathLike[str]) -> Path | None:
    """The folder holding cameras.{bin,txt} + images.{bin,txt}: `folder`, `folder/sparse/0`,
    `folder/sparse` or `folder/colmap/sparse/0`; None if there is none."""
    base = Path(folder)
    for sub in ("", "sparse/0", "sparse", "colmap/sparse/0", "distorted/sparse/0"):
        d = base / sub if sub else base
        for ext in ("bin", "txt"):
            if (d / f"cameras.{ext}").is_file() and (d / f"images.{ext}").is_file():
                return d
    return None


def read_colmap_views(folder: str | os.PathLike[str], *, sort: bool = True) -> list[ColmapView]:
    """Every registered image of a COLMAP model (binary preferred when both forms exist), each
    with its own camera at its own recorded size (the undistorted layout of `colmap
    image_undistorter` gives every image a camera of its own size; phone captures mix portrait
    and landscape cameras).

    Args:
        folder: the model folder, or a dataset folder holding `sparse/0` (see find_colmap_model).
        sort: order the images by name (a capture's video order); file order otherwise.

    Raises:
        FileNotFoundError: no model found. CaptureError: a malformed file (names it and the image).
    """
    model_dir = find_colmap_model(folder)
    if model_dir is None:
        raise FileNotFoundError(f"{folder}: no COLMAP model (cameras.bin/txt + images.bin/txt) found")
    if (model_dir / "cameras.bin").is_file() and (model_dir / "images.bin").is_file():
        intr = _read_cameras_bin(model_dir / "cameras.bin")
        images = _read_images_bin(model_dir / "images.bin")
    else:
        intr = _read_cameras_txt(model_dir / "cameras.txt")
        images = _read_images_txt(model_dir / "images.txt")
    if sort:
        images.sort(key=lambda im: im[0])
    out = []
    for name, cid, q, t in images:
        if cid not in intr:
            raise CaptureError(f"{model_dir}: image {name!r} refers to camera {cid}, which is not defined")
        model, w, h, params = intr[cid]
        fx, fy, cx, cy = _pinhole(model, params)
        if np.linalg.norm(q) == 0 or not np.all(np.isfinite(q)) or not np.all(np.isfinite(t)):
            raise CaptureError(f"{model_dir}: image {name!r} has an invalid pose")
        w2c = np.eye(4)
        w2c[:3, :3] = quat_to_matrix(q)
        w2c[:3, 3] = t
        try:
            cam = Camera(fx, fy, cx, cy, w, h, w2c)
        except ValueError as e:
            raise CaptureError(f"{model_dir}: image {name!r} (camera {cid}): {e}") from None
        out.append(ColmapView(name, cam, model, params, cid))
    if not out:
        raise CaptureError(f"{model_dir}: the model has no registered images")
    return out


def from_colmap(
    folder: str | os.PathLike[str],
    *,
    resolution: Sequence[int] | None = None,
    sort: bool = True,
) -> Cameras:
    """Cameras from a COLMAP sparse model (binary preferred when both forms exist).

    Every camera model is read through its pinhole part: fx, fy, cx, cy (one f for the SIMPLE_*
    and RADIAL* models). Distortion parameters are ignored (frames are rendered as ideal pinhole
    images; `morphgs fit` undistorts the photos, see docs/fit.md); fisheye models warn, since a
    pinhole is a poor stand-in for them.

    Args:
        folder: the model folder, or a dataset folder holding `sparse/0` (see find_colmap_model).
        resolution: (W, H) to render at: fx, cx scale by W'/W and fy, cy by H'/H; a camera of
            the other orientation (a portrait camera in a landscape path) is scaled uniformly to
            cover W x H and centre-cropped instead, so its pixels stay square
            (`trajectory.resize_camera`). None keeps the recorded size, which every camera must
            then share (`read_colmap_views` gives each image its own).
        sort: order the images by name (a capture's video order); file order otherwise.

    Returns:
        Cameras (OpenCV axes), one per registered image.

    Raises:
        FileNotFoundError: no model found. CaptureError (a MorphgsError): a malformed file, or
        cameras of several sizes without a resolution (names them).
    """
    res = check_resolution(resolution)
    views = read_colmap_views(folder, sort=sort)
    model_dir = find_colmap_model(folder)
    fisheye = sorted({v.model for v in views if v.model in _FISHEYE})
    if fisheye:
        warnings.warn(f"{model_dir}: fisheye camera model(s) {fisheye} are rendered as pinholes "
                      "(distortion ignored)", MorphgsWarning, stacklevel=2)
    return stack_resized([v.camera for v in views], res, str(model_dir))
