"""Small helpers shared by the trajectory readers and generators."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from morphgs.camera import Camera, Cameras

DEFAULT_RESOLUTION = (832, 480)


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
    """Resize every camera to `resolution` (or require one shared size) and stack them."""
    if not cams:
        raise ValueError(f"{source}: no cameras found")
    if resolution is not None:
        cams = [c.resized(*resolution) for c in cams]
    else:
        sizes = sorted({(c.width, c.height) for c in cams})
        if len(sizes) > 1:
            raise ValueError(f"{source}: cameras have different image sizes {sizes}; pass resolution=(W, H)")
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


def as_4x4(m: object, name: str) -> np.ndarray:
    """A (3,4) or (4,4) nested list -> (4,4) float64, with a clear error naming `name`."""
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 3x4 or 4x4 matrix of numbers") from None
    if a.shape == (3, 4):
        a = np.vstack([a, [0.0, 0.0, 0.0, 1.0]])
    if a.shape != (4, 4):
        raise ValueError(f"{name} must be a 3x4 or 4x4 matrix, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or Inf values")
    return a
