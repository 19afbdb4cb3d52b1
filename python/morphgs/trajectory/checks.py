"""The one validation of cameras read from a capture, for every reader (transforms.json, COLMAP
.txt / .bin, INRIA cameras.json, camera_path.json) and so for `fit`, `curate` and `ablate`.

A camera read from a file is refused with a `CaptureError` whose message starts with `where`
(the file and the frame or record, e.g. `transforms.json: frames[3] (images/0003.png)` or
`sparse/0/images.txt:12: image 5 'a.jpg'`) when:

- an entry is not a finite number, or is absurd: a rotation entry beyond 1 + ROTATION_TOL, a
  position or translation beyond MAX_COORDINATE, an image side beyond MAX_SIDE;
- a rotation is not orthonormal (largest entry of R^T R - I above ROTATION_TOL) or is a
  reflection (det < 0); a COLMAP quaternion's norm is off 1 by more than ROTATION_TOL;
  a 4x4 pose's last row is not (0, 0, 0, 1) within ROTATION_TOL;
- a focal length is not positive, or outside FOCAL_RANGE times the image's larger side;
- the principal point lies more than one image width (height) from the image centre;
- the image size is not a pair of positive integers;
- a distortion coefficient is not finite or beyond MAX_DISTORTION.

A rotation off by more than SNAP_TOL but within ROTATION_TOL (rounded digits) is replaced by the
nearest rotation; one within SNAP_TOL (float32 files, 1e-7) is used exactly as written, so
existing outputs keep their bytes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from morphgs.camera import Camera
from morphgs.trajectory._common import CaptureError

__all__ = [
    "FOCAL_RANGE",
    "MAX_COORDINATE",
    "MAX_SIDE",
    "ROTATION_TOL",
    "camera_from_c2w",
    "check_c2w",
    "check_distortion",
    "check_intrinsics",
    "check_position",
    "check_quaternion",
    "check_rotation",
    "check_size",
]

ROTATION_TOL = 1e-3
SNAP_TOL = 1e-6
MAX_COORDINATE = 1e8
MAX_SIDE = 100_000
FOCAL_RANGE = (1e-2, 1e4)  # times the larger image side: fields of view from 177 degrees to 0.006
MAX_DISTORTION = 1e6


def _numbers(where: str, what: str, values: Any, shape: tuple[int, ...]) -> np.ndarray:
    """`values` as a float64 array of `shape`, all finite; CaptureError otherwise."""
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise CaptureError(f"{where}: {what} must hold numbers, got {values!r}"[:300]) from None
    if a.shape != shape:
        raise CaptureError(f"{where}: {what} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CaptureError(f"{where}: {what} holds NaN or Inf ({_show(a)})")
    return a


def _show(a: np.ndarray) -> str:
    return np.array2string(a.reshape(-1), precision=4, separator=", ", max_line_width=10**6)


def _number(where: str, name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise CaptureError(f"{where}: {name} must be a number, got {v!r}")
    try:
        f = float(v)
    except OverflowError:  # a JSON integer beyond float's range
        f = math.inf
    if not math.isfinite(f):
        raise CaptureError(f"{where}: {name} must be finite, got {v!r}")
    return f


def check_size(where: str, width: Any, height: Any) -> tuple[int, int]:
    """(width, height) as positive integers up to MAX_SIDE."""
    w, h = _number(where, "image width", width), _number(where, "image height", height)
    if w != int(w) or h != int(h) or not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE):
        raise CaptureError(f"{where}: image size must be positive integers up to {MAX_SIDE}, got {width}x{height}")
    return int(w), int(h)


def check_intrinsics(where: str, fx: Any, fy: Any, cx: Any, cy: Any, width: Any,
                     height: Any) -> tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, width, height), checked: a focal length in FOCAL_RANGE times the larger
    image side, a principal point within one image width / height of the centre (None: the
    centre)."""
    w, h = check_size(where, width, height)
    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    f = [_number(where, n, v) for n, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy))]
    side = max(w, h)
    lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    if f[0] <= 0 or f[1] <= 0:
        raise CaptureError(f"{where}: focal lengths must be positive, got fx={f[0]:g} fy={f[1]:g}")
    if not (lo <= f[0] <= hi and lo <= f[1] <= hi):
        raise CaptureError(f"{where}: focal lengths fx={f[0]:g} fy={f[1]:g} are absurd for a {w}x{h} image "
                           f"(expected {lo:g} to {hi:g} px, {FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} times its "
                           "larger side)")
    if abs(f[2] - w / 2) > w or abs(f[3] - h / 2) > h:
        raise CaptureError(f"{where}: principal point ({f[2]:g}, {f[3]:g}) lies far outside the {w}x{h} image "
                           "(it may be at most one image width / height from the centre)")
    return f[0], f[1], f[2], f[3], w, h


def check_distortion(where: str, coeffs: dict[str, Any]) -> dict[str, float]:
    """Distortion coefficients by name: finite, each within MAX_DISTORTION."""
    out = {k: _number(where, k, v) for k, v in coeffs.items()}
    bad = {k: v for k, v in out.items() if abs(v) > MAX_DISTORTION}
    if bad:
        shown = ", ".join(f"{k}={v:g}" for k, v in bad.items())
        raise CaptureError(f"{where}: distortion coefficients {shown} are absurd (beyond {MAX_DISTORTION:g})")
    return out


def check_rotation(where: str, r: Any, *, what: str = "rotation") -> np.ndarray:
    """A (3,3) rotation: finite, orthonormal within ROTATION_TOL, det > 0. Returned as written
    within SNAP_TOL, else as the nearest rotation."""
    m = _numbers(where, what, r, (3, 3))
    big = np.abs(m).max()
    if big > 1 + ROTATION_TOL:
        raise CaptureError(f"{where}: {what} has an entry of {big:.6g}, beyond 1: not a rotation ({_show(m)})")
    err = float(np.abs(m.T @ m - np.eye(3)).max())
    if err > ROTATION_TOL:
        sv = np.linalg.svd(m, compute_uv=False)
        hint = ""
        if sv[-1] > 0 and sv[0] / sv[-1] - 1 < ROTATION_TOL:
            hint = f"; it is {sv[0]:.4g} times a rotation (a scaled camera): divide the scale out"
        raise CaptureError(f"{where}: {what} is not orthonormal (largest entry of R^T R - I is {err:.3g}, "
                           f"tolerance {ROTATION_TOL:g}){hint} ({_show(m)})")
    det = float(np.linalg.det(m))
    if det <= 0:
        raise CaptureError(f"{where}: {what} is a reflection (determinant {det:.3g}); cameras must be right-handed")
    if err <= SNAP_TOL:
        return m
    u, _, vt = np.linalg.svd(m)
    return np.asarray(u @ vt)


def check_position(where: str, t: Any, *, what: str = "position") -> np.ndarray:
    """A (3,) position or translation: finite, each entry within MAX_COORDINATE."""
    v = _numbers(where, what, t, (3,))
    if np.abs(v).max() > MAX_COORDINATE:
        raise CaptureError(f"{where}: {what} ({_show(v)}) is absurd (entries beyond {MAX_COORDINATE:g})")
    return v


def check_c2w(where: str, m: Any, *, what: str = "camera-to-world matrix") -> np.ndarray:
    """A (4,4) or (3,4) rigid pose: rotation (`check_rotation`), position (`check_position`) and a
    last row of (0, 0, 0, 1). Returned as (4,4)."""
    a = np.asarray(m, dtype=object)
    rows = a.shape[0] if a.ndim == 2 else 0
    full = _numbers(where, what, m, (rows, 4) if rows in (3, 4) else (4, 4))
    if rows == 4 and np.abs(full[3] - [0.0, 0.0, 0.0, 1.0]).max() > ROTATION_TOL:
        raise CaptureError(f"{where}: {what}'s last row must be (0, 0, 0, 1), got ({_show(full[3])})")
    out = np.eye(4)
    out[:3, :3] = check_rotation(where, full[:3, :3], what=f"{what}'s rotation")
    out[:3, 3] = check_position(where, full[:3, 3], what=f"{what}'s position")
    if rows == 4:
        out[3] = full[3]
    return out


def check_quaternion(where: str, q: Any) -> np.ndarray:
    """A (4,) unit quaternion (COLMAP's w, x, y, z): finite, norm within ROTATION_TOL of 1."""
    v = _numbers(where, "quaternion", q, (4,))
    if np.abs(v).max() > 1 + ROTATION_TOL:
        raise CaptureError(f"{where}: quaternion ({_show(v)}) is not a unit quaternion (an entry beyond 1)")
    n = float(np.sqrt(np.sum(v * v)))
    if abs(n - 1) > ROTATION_TOL:
        raise CaptureError(f"{where}: quaternion ({_show(v)}) is not a unit quaternion (norm {n:.6g}, "
                           f"tolerance {ROTATION_TOL:g})")
    return v


def camera_from_c2w(where: str, c2w: Any, *, fx: Any, fy: Any, width: Any, height: Any, cx: Any = None,
                    cy: Any = None, convention: str = "opencv") -> Camera:
    """A Camera from a camera-to-world pose and intrinsics, each checked (`check_c2w`,
    `check_intrinsics`; no cx / cy: the image centre); "opengl" poses (nerfstudio, Blender) are
    converted to OpenCV axes."""
    fx, fy, cx, cy, w, h = check_intrinsics(where, fx, fy, cx, cy, width, height)
    m = check_c2w(where, c2w)
    if convention not in ("opencv", "opengl"):
        raise ValueError(f"convention must be 'opencv' or 'opengl', got {convention!r}")
    return Camera.from_c2w(m, fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h,
                           convention="opengl" if convention == "opengl" else "opencv")
