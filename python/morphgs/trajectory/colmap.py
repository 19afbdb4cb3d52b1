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
from typing import Any, BinaryIO

import numpy as np

from morphgs._core import MorphgsWarning
from morphgs.camera import Camera, Cameras
from morphgs.trajectory._common import CaptureError, check_resolution, stack_resized
from morphgs.trajectory._rotations import quat_to_matrix
from morphgs.trajectory.checks import check_distortion, check_intrinsics, check_position, check_quaternion

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

@dataclass(frozen=True)
class _Intr:
    """One camera record: model, size, parameters, and where it is (file:line or record)."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]
    where: str


@dataclass(frozen=True)
class _Image:
    """One image record: name, camera id, quaternion (w, x, y, z), translation, and where."""

    name: str
    camera_id: int
    q: np.ndarray
    t: np.ndarray
    where: str


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


def _camera(cams: dict[int, _Intr], cid: int, model: str, w: int, h: int, params: tuple[float, ...],
            where: str) -> None:
    """Check one camera record (its pinhole part: `checks.check_intrinsics`) and add it."""
    if cid in cams:
        raise CaptureError(f"{where}: camera id {cid} is defined twice (first at {cams[cid].where})")
    fx, fy, cx, cy = _pinhole(model, params)
    check_intrinsics(where, fx, fy, cx, cy, w, h)
    first = 3 if model in _SINGLE_F else 4
    check_distortion(where, {f"{model} parameter {j + 1}": v for j, v in enumerate(params) if j >= first})
    cams[cid] = _Intr(model, w, h, params, where)


def _image(images: list[_Image], ids: dict[int, str], names: dict[str, str], iid: int, name: str, cid: int,
           q: Sequence[float], t: Sequence[float], where: str) -> None:
    """Check one image record (unique id and name, `checks.check_quaternion`,
    `checks.check_position`) and add it."""
    if not name:
        raise CaptureError(f"{where}: the image has no name")
    if iid in ids:
        raise CaptureError(f"{where}: image id {iid} is used twice (first at {ids[iid]})")
    if name in names:
        raise CaptureError(f"{where}: image name {name!r} is used twice (first at {names[name]})")
    ids[iid], names[name] = where, where
    qa = check_quaternion(where, q)
    ta = check_position(where, t, what="translation")
    images.append(_Image(name, cid, qa, ta, where))


def _read_cameras_txt(path: Path) -> dict[int, _Intr]:
    cams: dict[int, _Intr] = {}
    for ln, line in enumerate(_text_lines(path), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        where = f"{path}:{ln}"
        try:
            cid, model, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = tuple(float(v) for v in parts[4:])
        except (IndexError, ValueError):
            raise CaptureError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'") from None
        if model not in _BY_NAME:
            raise CaptureError(f"{where}: unknown camera model {model!r}")
        if len(params) != _BY_NAME[model][1]:
            raise CaptureError(f"{where}: model {model} takes {_BY_NAME[model][1]} params, got {len(params)}")
        _camera(cams, cid, model, w, h, params, f"{where}: camera {cid}")
    return cams


def _text_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as e:
        raise CaptureError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def _points_line(line: str) -> bool:
    """Whether `line` is an images.txt POINTS2D line: (X, Y, POINT3D_ID) triples, the id an
    integer (-1 for none). A pose line never is one (its third value is a quaternion entry)."""
    parts = line.split()
    return len(parts) % 3 == 0 and all(p.lstrip("-").isdigit() for p in parts[2::3])


def _read_images_txt(path: Path) -> list[_Image]:
    # Each image takes two lines: its pose, then its 2D points (which may be empty). As COLMAP's
    # reader, blank lines are skipped where a pose is expected, and the line after a pose is its
    # points. A file that ends right after a pose line is accepted (only 2D points would be lost).
    rows = [(ln, text.strip()) for ln, text in enumerate(_text_lines(path), 1)
            if not text.lstrip().startswith("#")]
    out: list[_Image] = []
    ids: dict[int, str] = {}
    names: dict[str, str] = {}
    i = 0
    while i < len(rows):
        ln, line = rows[i]
        if not line:
            i += 1
            continue
        parts = line.split()
        try:
            if len(parts) < 10:
                raise ValueError
            iid = int(parts[0])
            q = [float(v) for v in parts[1:5]]
            t = [float(v) for v in parts[5:8]]
            cid = int(parts[8])
            name = " ".join(parts[9:])
        except ValueError:
            raise CaptureError(f"{path}:{ln}: bad image line {line[:80]!r} (expected "
                               "'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', then a line of 2D points)") from None
        if i + 1 < len(rows) and not _points_line(rows[i + 1][1]):
            ln2, nxt = rows[i + 1]
            raise CaptureError(f"{path}:{ln2}: expected the 2D points of image {iid} (X Y POINT3D_ID triples, "
                               f"or an empty line), got {nxt[:80]!r}: each image takes two lines")
        _image(out, ids, names, iid, name, cid, q, t, f"{path}:{ln}: image {iid} {name!r}")
        i += 2
    return out


def _read(f: BinaryIO, fmt: str, path: Path, what: str) -> tuple[Any, ...]:
    size = struct.calcsize(fmt)
    b = f.read(size)
    if len(b) != size:
        raise CaptureError(f"{path}: file ends early, inside {what}")
    return struct.unpack(fmt, b)


def _count(f: BinaryIO, path: Path, what: str, smallest: int) -> int:
    """The record count of a binary model file, checked against the bytes that follow (each
    record takes at least `smallest`), so a count that lies allocates nothing."""
    (n,) = _read(f, "<Q", path, "the header")
    left = os.fstat(f.fileno()).st_size - f.tell()
    if n > left // smallest:
        raise CaptureError(f"{path}: the header says {n} {what}, but the {left} bytes that follow hold at most "
                           f"{left // smallest} (truncated or not a COLMAP file)")
    return int(n)


def _end(f: BinaryIO, path: Path, n: int, what: str) -> None:
    rest = len(f.read(1 << 16))
    if rest:
        raise CaptureError(f"{path}: bytes left after the {n} {what} its header announces (a damaged file, "
                           "or records the count leaves out)")


def _read_cameras_bin(path: Path) -> dict[int, _Intr]:
    cams: dict[int, _Intr] = {}
    with open(path, "rb") as f:
        n = _count(f, path, "cameras", 24 + 3 * 8)
        for k in range(n):
            rec = f"camera record {k + 1} of {n}"
            cid, mid, w, h = _read(f, "<iiQQ", path, rec)
            if mid not in _MODELS:
                raise CaptureError(f"{path}: {rec} (id {cid}): unknown camera model id {mid}")
            model, npar = _MODELS[mid]
            params = tuple(float(v) for v in _read(f, f"<{npar}d", path, rec))
            _camera(cams, int(cid), model, int(w), int(h), params, f"{path}: camera {cid} ({rec})")
        _end(f, path, n, "cameras")
    return cams


def _read_images_bin(path: Path) -> list[_Image]:
    out: list[_Image] = []
    ids: dict[int, str] = {}
    names: dict[str, str] = {}
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        n = _count(f, path, "images", 4 + 7 * 8 + 4 + 1 + 8)
        for k in range(n):
            rec = f"image record {k + 1} of {n}"
            vals = _read(f, "<i7di", path, rec)
            name = bytearray()
            while True:
                c = f.read(1)
                if not c:
                    raise CaptureError(f"{path}: file ends inside the name of {rec}")
                if c == b"\x00":
                    break
                name += c
            text = name.decode("utf-8", errors="replace")
            (npts,) = _read(f, "<Q", path, f"{rec} ({text!r})")
            if npts > (size - f.tell()) // 24:
                raise CaptureError(f"{path}: {rec} ({text!r}) says {npts} 2D points, more than the file holds "
                                   "(truncated?)")
            f.seek(24 * int(npts), os.SEEK_CUR)
            _image(out, ids, names, int(vals[0]), text, int(vals[8]), vals[1:5], vals[5:8],
                   f"{path}: image {vals[0]} {text!r} ({rec})")
        _end(f, path, n, "images")
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
        FileNotFoundError: no model found. CaptureError: a malformed file or an invalid camera
        (`trajectory.checks`; names the file and the line, or the binary record, and the image
        or camera).
    """
    model_dir = find_colmap_model(folder)
    if model_dir is None:
        raise FileNotFoundError(f"{folder}: no COLMAP model (cameras.bin/txt + images.bin/txt) found")
    binary = (model_dir / "cameras.bin").is_file() and (model_dir / "images.bin").is_file()
    if binary:
        intr = _read_cameras_bin(model_dir / "cameras.bin")
        images = _read_images_bin(model_dir / "images.bin")
    else:
        intr = _read_cameras_txt(model_dir / "cameras.txt")
        images = _read_images_txt(model_dir / "images.txt")
    if sort:
        images.sort(key=lambda im: im.name)
    out = []
    for im in images:
        cam_file = model_dir / ("cameras.bin" if binary else "cameras.txt")
        if im.camera_id not in intr:
            raise CaptureError(f"{im.where}: refers to camera {im.camera_id}, which is not defined in {cam_file}")
        c = intr[im.camera_id]
        fx, fy, cx, cy = _pinhole(c.model, c.params)
        w2c = np.eye(4)
        w2c[:3, :3] = quat_to_matrix(im.q)
        w2c[:3, 3] = im.t
        try:
            cam = Camera(fx, fy, cx, cy, c.width, c.height, w2c)
        except ValueError as e:
            raise CaptureError(f"{im.where} (camera {im.camera_id}): {e}") from None
        out.append(ColmapView(im.name, cam, c.model, c.params, im.camera_id))
    if not out:
        images_file = model_dir / ("images.bin" if binary else "images.txt")
        raise CaptureError(f"{images_file}: the model has no registered images")
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
