"""Readers for nerfstudio files: `transforms.json` (also DL3DV, instant-ngp, Blender) and
`camera_path.json` (the nerfstudio viewer's render paths).

Both store camera-to-world matrices in OpenGL camera axes (x right, y up, z backward); they are
converted to OpenCV axes (SPEC §3) by multiplying by diag(1,-1,-1,1) on the right.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from morphgs.camera import Camera, Cameras
from morphgs.trajectory._common import CaptureError, check_resolution, similarity_apply, stack_resized
from morphgs.trajectory.checks import camera_from_c2w, check_c2w, check_distortion, check_intrinsics, check_size

__all__ = ["TransformsFrame", "from_camera_path", "from_transforms_json", "read_transforms_frames"]

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass(frozen=True)
class TransformsFrame:
    """One frame of a transforms.json: its entry (the dict as written), its pinhole camera at its
    own size, the camera model ("OPENCV" unless `camera_model` says otherwise) and its
    distortion coefficients (k1 k2 k3 k4 p1 p2, per frame or shared; absent ones are 0)."""

    entry: dict[str, Any]
    camera: Camera
    camera_model: str
    distortion: dict[str, float]

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _load_json(path: str | os.PathLike[str]) -> dict[str, Any]:
    p = Path(path)
    try:
        with open(p, encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as e:
        raise CaptureError(f"{p}: not valid JSON ({e})") from None
    except UnicodeDecodeError as e:
        raise CaptureError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except RecursionError:
        raise CaptureError(f"{p}: JSON nested too deeply") from None
    if not isinstance(data, dict):
        raise CaptureError(f"{p}: expected a JSON object at the top level")
    return data


def _num(d: dict[str, Any], key: str, path: Path, where: str) -> float:
    v = d[key]
    try:
        f = math.inf if isinstance(v, bool) or not isinstance(v, (int, float)) else float(v)
    except OverflowError:  # a JSON integer beyond float's range
        f = math.inf
    if not math.isfinite(f):
        raise CaptureError(f"{path}: {where}field {key!r} must be a finite number, got {str(v)[:40]}")
    return f


def _photo_size(root: Path, file_path: Any) -> tuple[int, int] | None:
    """The (W, H) of a frame's photo read from its header, as instant-ngp does when a
    transforms.json (the Blender layout) gives no `w`/`h`; None when there is no such photo."""
    if not isinstance(file_path, str) or not file_path:
        return None
    p = root / file_path
    cands = [p] if p.suffix else [p] + [p.with_suffix(e) for e in (".png", ".jpg", ".jpeg", ".JPG", ".PNG")]
    for c in cands:
        if c.is_file():
            try:
                from PIL import Image

                with Image.open(c) as im:
                    return int(im.size[0]), int(im.size[1])
            except (OSError, ValueError):
                return None
    return None


def _intrinsics(frame: dict[str, Any], meta: dict[str, Any], path: Path, i: int,
                where: str) -> tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, w, h) with per-frame values overriding the shared ones, checked
    (`checks.check_intrinsics`)."""

    def get(key: str) -> float | None:
        for src, prefix in ((frame, f"frames[{i}]."), (meta, "")):
            if key in src:
                return _num(src, key, path, prefix)
        return None

    w, h = get("w"), get("h")
    if w is None or h is None:
        size = _photo_size(path.parent, frame.get("file_path"))
        if size is None:
            raise CaptureError(f"{where}: no image size (fields 'w' and 'h', shared or per frame, or the "
                               "frame's photo to read it from)")
        w, h = float(size[0]), float(size[1])
    w, h = check_size(where, w, h)
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None and fy is None:
        for key, side in (("camera_angle_x", w), ("camera_angle_y", h)):
            angle = get(key)
            if angle is None:
                continue
            if not 0 < angle < math.pi:
                raise CaptureError(f"{where}: {key} must be in (0, pi) radians, got {angle}")
            f = 0.5 * side / math.tan(0.5 * angle)
            fx, fy = (f, fy) if key == "camera_angle_x" else (fx, f)
    fx = fx if fx is not None else fy
    fy = fy if fy is not None else fx
    if fx is None or fy is None:
        raise CaptureError(f"{where}: no focal length ('fl_x'/'fl_y' or 'camera_angle_x')")
    cx, cy = get("cx"), get("cy")
    return check_intrinsics(where, fx, fy, cx, cy, w, h)


def from_transforms_json(
    path: str | os.PathLike[str],
    *,
    resolution: Sequence[int] | None = None,
    frame: Literal["colmap", "file"] = "colmap",
    dataparser_transforms: str | os.PathLike[str] | None = None,
    sort: bool = True,
) -> Cameras:
    """Cameras from a nerfstudio / DL3DV / instant-ngp `transforms.json`.

    Intrinsics: `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` at the top level (shared) or in each frame
    (per-frame values win); `camera_angle_x`/`camera_angle_y` (Blender) when no focal length is
    given; a missing `cx`/`cy` means the image centre. Distortion coefficients (k1, k2, p1, p2,
    ...) are ignored: frames are rendered as ideal pinhole images (`morphgs fit` undistorts the
    photos, see docs/fit.md).

    Poses and frames (exactly what happens): each `transform_matrix` is an OpenGL camera-to-world
    matrix in the frame of the file. ns-process-data writes `applied_transform` (3x4, A) with
    c2w_file = A @ c2w_colmap, so

    - `frame="colmap"` (default) undoes it: c2w = A^-1 @ c2w_file. The cameras then live in the
      COLMAP world frame, where splats trained on that COLMAP reconstruction are (INRIA 3DGS,
      gsplat's trainer, the DL3DV releases). Without `applied_transform` nothing changes.
    - `frame="file"` keeps the poses as written.
    - `dataparser_transforms=path` (nerfstudio's `dataparser_transforms.json`, {"transform": 3x4
      T, "scale": s}) maps the file-frame poses into the frame of a splatfacto model:
      c2w = diag(s,s,s,1) @ T @ c2w_file (the orientation is rotated by T, the position moved and
      scaled). `ns-export gaussian-splat` writes the model's Gaussians in that frame, so this is
      the option for splats exported by nerfstudio. It implies `frame="file"`.

    Args:
        path: the JSON file.
        resolution: (W, H) to render at: fx, cx scale by W'/W and fy, cy by H'/H (a frame of
            the other orientation is scaled uniformly and centre-cropped, see
            `trajectory.resize_camera`). None keeps the file's size (all frames must share one;
            `read_transforms_frames` gives each its own).
        frame: "colmap" or "file", see above.
        dataparser_transforms: optional nerfstudio dataparser_transforms.json, see above.
        sort: order the frames by `file_path` as nerfstudio does (file order otherwise).

    Returns:
        Cameras in OpenCV axes.

    Raises:
        CaptureError (a MorphgsError): malformed file (names the field). ValueError: bad arguments.
        FileNotFoundError: missing file.
    """
    res = check_resolution(resolution)
    frames = read_transforms_frames(path, frame=frame, dataparser_transforms=dataparser_transforms, sort=sort)
    return stack_resized([f.camera for f in frames], res, str(path))


def read_transforms_frames(
    path: str | os.PathLike[str],
    *,
    frame: Literal["colmap", "file"] = "colmap",
    dataparser_transforms: str | os.PathLike[str] | None = None,
    sort: bool = True,
) -> list[TransformsFrame]:
    """Every frame of a transforms.json with its own camera at its own size (`w`/`h` per frame
    win over the shared ones), its camera model and distortion coefficients. Poses and `frame`
    as in `from_transforms_json`.

    Raises:
        CaptureError (a MorphgsError): a malformed file (names the field). ValueError: bad
        arguments. FileNotFoundError: missing file.
    """
    p = Path(path)
    if frame not in ("colmap", "file"):
        raise ValueError(f"frame must be 'colmap' or 'file', got {frame!r}")
    meta = _load_json(p)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CaptureError(f"{p}: field 'frames' must be a non-empty list")
    # messages name a frame by its index in the file, whatever the order
    order = list(range(len(frames)))
    if sort:
        order.sort(key=lambda i: str(frames[i].get("file_path", "")) if isinstance(frames[i], dict) else "")
    world = np.eye(4)
    if dataparser_transforms is not None:
        dpp = Path(dataparser_transforms)
        dp = _load_json(dpp)
        if "transform" not in dp or "scale" not in dp:
            raise CaptureError(f"{dpp}: needs fields 'transform' (3x4) and 'scale'")
        t = check_c2w(str(dpp), dp["transform"], what="transform")
        s = _num(dp, "scale", dpp, "")
        if not 0 < s <= 1e8:
            raise CaptureError(f"{dpp}: field 'scale' must be positive (at most 1e8), got {s}")
        world = np.diag([s, s, s, 1.0]) @ t
    elif frame == "colmap" and "applied_transform" in meta:
        # checked to be rigid, so invertible (inverted as before: the same bytes)
        world = np.linalg.inv(check_c2w(str(p), meta["applied_transform"], what="applied_transform"))
    wheres: list[str] = []
    c2ws = []
    for i in order:
        fr = frames[i]
        fp = fr.get("file_path") if isinstance(fr, dict) else None
        where = f"{p}: frames[{i}]" + (f" ({fp})" if isinstance(fp, str) and fp else "")
        if not isinstance(fr, dict) or "transform_matrix" not in fr:
            raise CaptureError(f"{where} has no 'transform_matrix'")
        c2ws.append(check_c2w(where, fr["transform_matrix"], what="transform_matrix"))
        wheres.append(where)
    c2w = np.stack(c2ws) @ _GL_TO_CV
    try:
        c2w = similarity_apply(world, c2w)
    except ValueError as e:
        raise CaptureError(f"{p}: {e}") from None
    out: list[TransformsFrame] = []
    for k, i in enumerate(order):
        fr, where = frames[i], wheres[k]
        fx, fy, cx, cy, w, h = _intrinsics(fr, meta, p, i, where)
        try:
            cam = Camera.from_c2w(c2w[k], fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)
        except ValueError as e:
            raise CaptureError(f"{where}: {e}") from None
        model = fr.get("camera_model", meta.get("camera_model", "OPENCV"))
        if not isinstance(model, str):
            raise CaptureError(f"{where}: camera_model must be a string, got {model!r}")
        dist = {}
        for key in _DISTORTION_KEYS:
            src = fr if key in fr else meta
            dist[key] = _num(src, key, p, f"frames[{i}]." if src is fr else "") if key in src else 0.0
        dist = check_distortion(where, dist)
        out.append(TransformsFrame(fr, cam, model.upper(), dist))
    return out


def from_camera_path(
    path: str | os.PathLike[str],
    *,
    resolution: Sequence[int] | None = None,
) -> Cameras:
    """Cameras from a nerfstudio viewer `camera_path.json`.

    Reads `render_width`/`render_height` (or `aspect` times the height when the width is
    missing) and, per keyframe of `camera_path`, `camera_to_world` (16 numbers, a row-major 4x4,
    OpenGL axes) and `fov` (vertical field of view in degrees, as nerfstudio's renderer reads it:
    f = H / (2 tan(fov/2)), principal point at the image centre). Poses are used as written: they
    are in the frame of the model the path was made for. Only perspective paths are supported.

    Args:
        path: the JSON file.
        resolution: optional (W, H) to render at instead of render_width/height.

    Raises:
        MorphgsError: malformed file. FileNotFoundError: missing file.
    """
    p = Path(path)
    res = check_resolution(resolution)
    meta = _load_json(p)
    ctype = str(meta.get("camera_type", "perspective")).lower()
    if ctype != "perspective":
        raise CaptureError(f"{p}: camera_type {ctype!r} is not supported (only 'perspective')")
    path_list = meta.get("camera_path")
    if not isinstance(path_list, list) or not path_list:
        raise CaptureError(f"{p}: field 'camera_path' must be a non-empty list")
    if "render_height" not in meta:
        raise CaptureError(f"{p}: field 'render_height' is missing")
    h = _num(meta, "render_height", p, "")
    if "render_width" in meta:
        w = _num(meta, "render_width", p, "")
    else:
        aspect = _num(path_list[0], "aspect", p, "camera_path[0].") if isinstance(path_list[0], dict) and "aspect" in path_list[0] else None
        if aspect is None:
            raise CaptureError(f"{p}: neither 'render_width' nor an 'aspect' is given")
        w = aspect * h
        w = round(w) if math.isfinite(w) else w
    w, h = check_size(f"{p}: render size", w, h)
    cams = []
    for i, kf in enumerate(path_list):
        where = f"{p}: camera_path[{i}]"
        if not isinstance(kf, dict) or "camera_to_world" not in kf or "fov" not in kf:
            raise CaptureError(f"{where} needs 'camera_to_world' and 'fov'")
        try:
            flat = np.asarray(kf["camera_to_world"], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError, OverflowError):
            raise CaptureError(f"{where}.camera_to_world must hold 16 numbers") from None
        if flat.size != 16:
            raise CaptureError(f"{where}.camera_to_world must hold 16 numbers, got {flat.size}")
        fov = _num(kf, "fov", p, f"camera_path[{i}].")
        if not 0 < fov < 180:
            raise CaptureError(f"{where}.fov must be in (0, 180) degrees, got {fov}")
        f = 0.5 * h / math.tan(math.radians(fov) / 2)
        cams.append(camera_from_c2w(where, flat.reshape(4, 4), fx=f, fy=f, width=w, height=h, convention="opengl"))
    return stack_resized(cams, res, str(p))
