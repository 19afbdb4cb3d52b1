"""Camera paths made from scratch: ellipse/orbit, forward-facing spiral, and a path framing a
scene that has no cameras."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from morphgs.camera import Camera, Cameras, look_at_c2w
from morphgs.trajectory._common import DEFAULT_RESOLUTION, check_resolution

__all__ = ["around_cameras", "camera_focus", "ellipse", "for_scene", "orbit", "robust_bounds", "spiral"]


def _focal(fov_y_degrees: float, height: int) -> float:
    if not 0.0 < fov_y_degrees < 180.0:
        raise ValueError(f"fov_y_degrees must be in (0, 180), got {fov_y_degrees}")
    return 0.5 * height / math.tan(math.radians(fov_y_degrees) / 2)


def _check_frames(n_frames: int) -> int:
    n = int(n_frames)
    if n != n_frames or n < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    return n


def _unit(v: npt.ArrayLike, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"{name} must be a finite non-zero 3-vector")
    return a / n


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to `up` (right-handed with it)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return e1, e2


def ellipse(
    center: npt.ArrayLike,
    radii: float | Sequence[float],
    height: float,
    n_frames: int,
    *,
    target: npt.ArrayLike | None = None,
    up: npt.ArrayLike = (0.0, 0.0, 1.0),
    start_degrees: float = 0.0,
    arc_degrees: float = 360.0,
    fov_y_degrees: float = 50.0,
    resolution: Sequence[int] = DEFAULT_RESOLUTION,
) -> Cameras:
    """Cameras on an ellipse around `center`, `height` above it along `up`, looking at `target`.

    Positions: center + up*height + a cos(th) e1 + b sin(th) e2 for th running from start over
    `arc_degrees` (a full turn does not repeat its first frame). Each camera looks at `target`
    (default `center`) with `up` as the world's up.

    Args:
        center: (3,) centre of the ellipse.
        radii: one radius (a circle) or the two semi-axes (a, b).
        height: offset of the ellipse's plane along `up`.
        n_frames: number of cameras.
        target: look-at point.
        up: world up direction (z-up by default).
        start_degrees, arc_degrees: where the path starts and how far it goes.
        fov_y_degrees: vertical field of view.
        resolution: (W, H).

    Returns:
        Cameras.
    """
    n = _check_frames(n_frames)
    res = check_resolution(resolution)
    assert res is not None
    w, h = res
    c = np.asarray(center, dtype=np.float64).reshape(3)
    r = np.broadcast_to(np.asarray(radii, dtype=np.float64).reshape(-1), (2,))
    if np.any(~np.isfinite(r)) or np.any(r <= 0) or not np.all(np.isfinite(c)):
        raise ValueError(f"ellipse: need a finite centre and positive radii, got {center!r}, {radii!r}")
    u = _unit(up, "up")
    tgt = c if target is None else np.asarray(target, dtype=np.float64).reshape(3)
    e1, e2 = _basis(u)
    full = abs(arc_degrees) >= 360.0 - 1e-9
    steps = n if full else max(n - 1, 1)
    th = np.radians(start_degrees + arc_degrees * np.arange(n) / steps)
    f = _focal(fov_y_degrees, h)
    k = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    c2w = []
    for t in th:
        eye = c + u * height + r[0] * math.cos(t) * e1 + r[1] * math.sin(t) * e2
        c2w.append(look_at_c2w(eye, tgt, u))
    return Cameras.from_c2w(np.stack(c2w), K=k, width=w, height=h)


def orbit(
    center: npt.ArrayLike,
    radius: float,
    height: float,
    n_frames: int,
    **kwargs: Any,
) -> Cameras:
    """A circular orbit: `ellipse(center, radius, height, n_frames, **kwargs)`."""
    return ellipse(center, float(radius), height, n_frames, **kwargs)


def spiral(
    base: Camera,
    n_frames: int,
    *,
    focus_distance: float,
    radius: float | Sequence[float] = 0.1,
    rotations: float = 2.0,
) -> Cameras:
    """A forward-facing spiral (LLFF style) around a base camera.

    Position k: base centre + R_base @ (rx cos th, ry sin th, rz sin(th/2)) in the base camera's
    axes, th = 2 pi rotations k / n; every camera looks at the point `focus_distance` in front of
    the base camera, with the base camera's up (-y) as up. Intrinsics and size are the base's.

    Args:
        base: the central camera.
        n_frames: number of cameras.
        focus_distance: distance of the look-at point along the base camera's view axis.
        radius: amplitude (one value, or (rx, ry, rz)) in world units.
        rotations: number of turns over the path.
    """
    n = _check_frames(n_frames)
    if not focus_distance > 0:
        raise ValueError(f"focus_distance must be > 0, got {focus_distance}")
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64).reshape(-1), (3,))
    c2w0 = base.camera_to_world
    rot, centre = c2w0[:3, :3], c2w0[:3, 3]
    focus = centre + rot[:, 2] * focus_distance
    up = -rot[:, 1]
    th = 2 * math.pi * rotations * np.arange(n) / n
    offs = np.stack([r[0] * np.cos(th), r[1] * np.sin(th), r[2] * np.sin(th / 2)], 1)
    c2w = np.stack([look_at_c2w(centre + rot @ o, focus, up) for o in offs])
    return Cameras.from_c2w(c2w, K=base.K, width=base.width, height=base.height)


def robust_bounds(
    points: npt.ArrayLike,
    *,
    percentiles: tuple[float, float] = (2.0, 98.0),
    weights: npt.ArrayLike | None = None,
    weight_threshold: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis percentile bounds of (N,3) points, so a few floaters do not count.

    Points whose weight (e.g. opacity) is below `weight_threshold` are left out when enough
    others remain.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(p), axis=1)
    if weights is not None:
        wgt = np.asarray(weights, dtype=np.float64).reshape(-1)
        if wgt.shape[0] != p.shape[0]:
            raise ValueError(f"robust_bounds: {wgt.shape[0]} weights for {p.shape[0]} points")
        heavy = keep & (wgt >= weight_threshold)
        if heavy.sum() >= 16:
            keep = heavy
    p = p[keep]
    if len(p) == 0:
        raise ValueError("robust_bounds: no finite points")
    lo, hi = percentiles
    if not 0.0 <= lo < hi <= 100.0:
        raise ValueError(f"percentiles must satisfy 0 <= lo < hi <= 100, got {percentiles}")
    return np.percentile(p, lo, axis=0), np.percentile(p, hi, axis=0)


# Every scene file morphgs.load reads comes back in RDF axes (x right, y down, z front: PLY,
# INRIA / COLMAP worlds, SOG, .splat, SceneSplat; glTF's LUF and spz's RUB are converted by the
# loaders), so a loaded file's up is -y; the built-in synthetic scenes are z-up.
FILE_UP = (0.0, -1.0, 0.0)
BUILTIN_UP = (0.0, 0.0, 1.0)
_NAMED = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
          "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}


def parse_up(text: str) -> np.ndarray:
    """An up vector from `+x`, `-y`, ... or `X,Y,Z` (normalised); ValueError otherwise."""
    t = text.strip().lower()
    if t in _NAMED:
        return np.asarray(_NAMED[t])
    if t in ("x", "y", "z"):
        return np.asarray(_NAMED["+" + t])
    try:
        v = np.asarray([float(x) for x in t.split(",")], np.float64)
    except ValueError:
        raise ValueError(f"up {text!r}: expected +x, -x, +y, -y, +z, -z or X,Y,Z") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise ValueError(f"up {text!r}: expected three finite numbers, not all zero")
    return v / np.linalg.norm(v)


def scene_up(scene: Any, rule: str = "file") -> tuple[np.ndarray, str]:
    """The up vector of a scene without cameras, and the reason.

    Rules:
        "file": the loaders' convention (`FILE_UP`, -y: every format is returned in RDF axes).
        "builtin": +z (the synthetic scenes).
        "scene": from the Gaussians alone: the principal axis of least spread of the centres
            (opacity >= 0.1; a ground-level scene is wider than tall), signed as gsplat's
            COLMAP parser does, so that the median lies below the mean (more content low, the
            ground). For tall, narrow subjects it is wrong; give the axis then.
        "+x" ... "-z" or "X,Y,Z": that vector.
    """
    if rule == "file":
        return np.asarray(FILE_UP), "file convention (RDF axes: up is -y)"
    if rule == "builtin":
        return np.asarray(BUILTIN_UP), "built-in synthetic scene (z-up)"
    if rule == "scene":
        means = np.asarray(getattr(scene, "means", scene), np.float64)
        op = getattr(scene, "opacities", None)
        if op is not None:
            keep = np.asarray(op).reshape(-1) >= 0.1
            if keep.sum() >= 10:
                means = means[keep]
        c = means - means.mean(axis=0)
        _, vecs = np.linalg.eigh(c.T @ c)
        up = vecs[:, 0]
        h = c @ up
        if np.median(h) > np.mean(h):
            up = -up
        return up, "scene: principal axis of least spread, signed towards the sparser side"
    return parse_up(rule), f"given ({rule})"


def for_scene(
    scene: Any,
    n_frames: int,
    *,
    resolution: Sequence[int] = DEFAULT_RESOLUTION,
    fov_y_degrees: float = 50.0,
    up: npt.ArrayLike | str = (0.0, 0.0, 1.0),
    elevation_degrees: float = 25.0,
    start_degrees: float = 0.0,
    arc_degrees: float = 360.0,
    percentiles: tuple[float, float] = (2.0, 98.0),
    margin: float = 1.1,
) -> Cameras:
    """An orbit framing a scene that has no cameras of its own.

    The framed box is the per-axis `percentiles` of the Gaussian centres (Gaussians with opacity
    below 0.1 left out), so a few far floaters neither move the centre nor push the camera away.
    The camera circles the box centre at `elevation_degrees` above the plane orthogonal to `up`,
    at the distance where the box's bounding sphere fits the narrower field of view, times
    `margin`.

    Args:
        scene: a GaussianScene (or an (N,3) array of centres).
        n_frames: number of cameras.
        resolution: (W, H).
        fov_y_degrees: vertical field of view.
        up: world up: a vector (the default +z suits the synthetic scenes), or a rule of
            `scene_up`: "file" (-y: every loaded scene file is in RDF axes), "scene" (from the
            Gaussians), "+x" ... "-z", "X,Y,Z".
        elevation_degrees: camera elevation above the box centre.
        start_degrees, arc_degrees: the part of the circle the path covers.
        percentiles: robust bound percentiles.
        margin: >= 1 leaves room around the content.

    Returns:
        Cameras.
    """
    res = check_resolution(resolution)
    assert res is not None
    if isinstance(up, str):
        up = scene_up(scene, up)[0]
    means = getattr(scene, "means", scene)
    weights = getattr(scene, "opacities", None)
    lo, hi = robust_bounds(means, percentiles=percentiles, weights=weights)
    centre = (lo + hi) / 2
    sphere = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    w, h = res
    half_y = math.radians(fov_y_degrees) / 2
    half_x = math.atan(math.tan(half_y) * w / h)
    dist = margin * sphere / math.sin(min(half_x, half_y))
    el = math.radians(elevation_degrees)
    return ellipse(centre, dist * math.cos(el), dist * math.sin(el), n_frames, target=centre, up=up,
                   start_degrees=start_degrees, arc_degrees=arc_degrees, fov_y_degrees=fov_y_degrees,
                   resolution=res)


def camera_focus(cameras: Cameras) -> tuple[np.ndarray, np.ndarray, bool]:
    """Where recorded cameras look, and their up: (focus point, unit up, converged).

    The focus is the least-squares point nearest to every camera's optical axis (the
    point-of-interest of nerfstudio's and instant-ngp's orbit viewers): the solution of
    sum_i (I - d_i d_i^T)(p - c_i) = 0 over camera centres c_i and viewing directions d_i. The
    up is the mean of the cameras' up vectors (-y of each camera, OpenCV axes), normalised.
    `converged` is False when the axes are nearly parallel (a forward-facing capture) or the
    point lies behind most cameras; the focus is then the mean camera centre moved along the mean
    viewing direction by twice the cameras' spread (never a point at infinity).
    """
    c2w = np.linalg.inv(np.asarray(cameras.world_to_camera, np.float64))
    centres = c2w[:, :3, 3]
    dirs = c2w[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    ups = -c2w[:, :3, 1]
    up = ups.mean(axis=0)
    n = float(np.linalg.norm(up))
    up = up / n if n > 1e-9 else -c2w[0, :3, 1]
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, dirs):
        m = np.eye(3) - np.outer(d, d)
        a += m
        b += m @ c
    eig = np.linalg.eigvalsh(a)
    converged = bool(eig[0] > 1e-3 * max(eig[-1], 1e-12))
    focus = np.linalg.solve(a, b) if converged else None
    if focus is not None:
        ahead = np.einsum("ij,ij->i", focus[None, :] - centres, dirs)
        converged = bool(np.median(ahead) > 0)
    if focus is None or not converged:
        mean_dir = dirs.mean(axis=0)
        mean_dir /= max(float(np.linalg.norm(mean_dir)), 1e-12)
        spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
        focus = centres.mean(axis=0) + mean_dir * max(spread, 1e-3) * 2.0
        converged = False
    return focus, up, converged


def around_cameras(
    cameras: Cameras,
    n_frames: int,
    *,
    resolution: Sequence[int] | None = None,
    start_degrees: float = 0.0,
    arc_degrees: float = 360.0,
    elevation_degrees: float | None = None,
) -> Cameras:
    """An orbit through the part of a scene that recorded cameras looked at.

    Circles `camera_focus(cameras)` around the cameras' mean up, at their median distance to
    the focus, at their median elevation above it (or `elevation_degrees`), with the median
    vertical field of view of the recorded cameras. A real capture's Gaussians spread far
    beyond its subject (background, sky, floaters), so a box around the centres (`for_scene`)
    frames mostly emptiness; the cameras say where the subject is.

    Args:
        cameras: the recorded cameras (at least one).
        n_frames: number of cameras of the orbit.
        resolution: (W, H); default the first recorded camera's size.
        start_degrees, arc_degrees: the part of the circle the path covers (0 degrees: the
            direction of the first recorded camera).
        elevation_degrees: elevation above the focus; default the recorded cameras' median.

    Returns:
        Cameras.
    """
    if len(cameras) < 1:
        raise ValueError("around_cameras: no cameras")
    res = check_resolution(resolution) or (int(cameras.width), int(cameras.height))
    focus, up, _ = camera_focus(cameras)
    c2w = np.linalg.inv(np.asarray(cameras.world_to_camera, np.float64))
    rel = c2w[:, :3, 3] - focus
    height = rel @ up
    flat = rel - height[:, None] * up
    dist = float(np.median(np.linalg.norm(rel, axis=1)))
    if not np.isfinite(dist) or dist <= 0:
        raise ValueError("around_cameras: the cameras sit at their own focus point")
    if elevation_degrees is None:
        el = float(np.median(np.arctan2(height, np.linalg.norm(flat, axis=1))))
    else:
        el = math.radians(elevation_degrees)
    el = float(np.clip(el, math.radians(-80.0), math.radians(80.0)))
    k = np.asarray(cameras.K, np.float64)
    fov_y = float(np.median(2.0 * np.degrees(np.arctan(0.5 * cameras.height / k[:, 1, 1]))))
    e1, e2 = _basis(up)
    f0 = flat[0]
    if float(np.linalg.norm(f0)) > 1e-9:
        # start at the first recorded camera's side: rotate (e1, e2) so e1 points at it
        a0 = math.atan2(float(f0 @ e2), float(f0 @ e1))
        start_degrees = start_degrees + math.degrees(a0)
    return ellipse(focus, dist * math.cos(el), dist * math.sin(el), n_frames, target=focus, up=up,
                   start_degrees=start_degrees, arc_degrees=arc_degrees, fov_y_degrees=fov_y,
                   resolution=res)
