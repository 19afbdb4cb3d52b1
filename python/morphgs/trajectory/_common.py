"""Small helpers shared by the trajectory readers and generators."""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from morphgs._core import MorphgsError, MorphgsWarning
from morphgs.camera import Camera, Cameras

DEFAULT_RESOLUTION = (832, 480)


class CaptureError(MorphgsError):
    """A capture (cameras file, COLMAP model, images, masks) that cannot be used as it is; the
    message names the file, the field or image, and what to do. A ValueError, as every
    MorphgsError."""


STRETCH_WARN = 1.05  # aspect ratios within 5 % are resized per axis (DL3DV's 16:9 at 832x480 is 2.6 %)


def _aspect_gap(cam: Camera, width: int, height: int) -> float:
    """How far `cam`'s aspect ratio is from `width` x `height`'s, as a factor >= 1."""
    r = (cam.width / cam.height) / (width / height)
    return max(r, 1.0 / r)


def resize_camera(cam: Camera, width: int, height: int) -> Camera:
    """`cam` rendering at `width` x `height`, pixels kept square.

    A camera within 5 % of the target's aspect ratio: fx, cx scale by W'/W and fy, cy by H'/H
    (`Camera.resized`, exact for the same aspect). Any other (a 4:3 photo in a 16:9 path, a
    portrait phone frame in a landscape one): one uniform scale s = max(W'/W, H'/H) so the new
    frame is covered, and a centred crop (the principal point shifts by half the overhang), so
    nothing is stretched and the centre of the view stays the centre of the frame.
    """
    if _aspect_gap(cam, width, height) <= STRETCH_WARN:
        return cam.resized(width, height)
    s = max(width / cam.width, height / cam.height)
    return Camera(cam.fx * s, cam.fy * s, cam.cx * s - (cam.width * s - width) / 2,
                  cam.cy * s - (cam.height * s - height) / 2, width, height, cam.world_to_camera, cam.near, cam.far)


class CropWarning(MorphgsWarning):
    """`warn_stretch`'s warning: cameras centre-cropped to another aspect (a MorphgsWarning, so
    the command line shows it as one; its own class so a caller that has said it can filter it)."""


def warn_stretch(cams: Sequence[Camera], width: int, height: int, source: str) -> None:
    """Warn (CropWarning, naming `source`) when `resize_camera` crops cameras of `cams` of the
    target's orientation at `width` x `height` (a capture whose aspect ratio is more than 5 % from
    the size's), with how much of the view is kept and a size of the capture's aspect that keeps
    it whole. (Cameras of the other orientation are cropped without a word: no size suits both.)"""
    worst, cam = 1.0, None
    for c in cams:
        if c.width == c.height or width == height or (c.width > c.height) == (width > height):
            r = _aspect_gap(c, width, height)
            if r > worst:
                worst, cam = r, c
    if cam is None or worst <= STRETCH_WARN:
        return
    w2 = max(2, int(round(height * cam.width / cam.height / 2.0)) * 2)
    warnings.warn(f"{source}: cameras of {cam.width}x{cam.height} (aspect {cam.width / cam.height:.3g}) rendered at "
                  f"{width}x{height} (aspect {width / height:.3g}) are centre-cropped to it, keeping {100 / worst:.0f} % "
                  f"of the view; pass a size of the capture's aspect to keep it whole, e.g. --size {w2}x{height}",
                  CropWarning, stacklevel=3)


def check_resolution(resolution: Sequence[int] | None) -> tuple[int, int] | None:
    """Validate a (width, height) pair of positive integers (or None)."""
    if resolution is None:
        return None
    try:
        w, h = (int(v) for v in resolution)
    except (TypeError, ValueError):
        raise ValueError(f"resolution must be (width, height), got {resolution!r}") from None
    if w <= 0 or h <= 0 or (w, h) != tuple(resolution):
        raise ValueError(f"resolution must be positive integers (width, height), got {resolution!r}")
    return w, h


def stack_resized(cams: Sequence[Camera], resolution: tuple[int, int] | None, source: str) -> Cameras:
    """Resize every camera to `resolution` (`resize_camera`; or require one shared size) and stack
    them."""
    if not cams:
        raise CaptureError(f"{source}: no cameras found")
    if resolution is not None:
        warn_stretch(cams, *resolution, source)
        cams = [resize_camera(c, *resolution) for c in cams]
    else:
        sizes = sorted({(c.width, c.height) for c in cams})
        if len(sizes) > 1:
            shown = ", ".join(f"{w}x{h}" for w, h in sizes[:6]) + (", ..." if len(sizes) > 6 else "")
            raise CaptureError(f"{source}: cameras have {len(sizes)} different image sizes ({shown}); a Cameras "
                               "path needs one: pass resolution=(W, H) (curate's --size), or read each image's "
                               "own camera with trajectory.read_colmap_views / morphgs fit")
    return Cameras.from_list(cams)


def similarity_apply(m: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Move camera-to-world poses (F,4,4) by a world transform m (4,4) = [s R | t].

    Positions go through m fully (rotation, uniform scale, translation); orientations through R
    only, so the result stays a rigid camera pose.
    """
    a = m[:3, :3]
    u, sv, vt = np.linalg.svd(a)
    r = u @ vt
    if np.linalg.det(r) <= 0:
        raise ValueError("the world transform is a reflection; cameras would become left-handed")
    if sv.max() - sv.min() > 1e-6 * max(sv.max(), 1e-12):
        raise ValueError(f"the world transform must be a similarity (uniform scale), singular values {sv}")
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[:, :3, :3] = r @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] @ a.T + m[:3, 3]
    return out
