"""Random initialisation where the scene is: points along the training cameras' rays
(docs/fit.md, "Initialisation").

The box of camera centres (`init="box"`) works for captures that circle their subject; for a
forward-facing capture (LLFF style: every camera on a small patch, looking the same way) the
scene lies far outside that box and a fit from it learns a haze. Points along the rays of the
training views are, by construction, inside the frustums the loss sees, whatever the layout.

The rule (documented, deterministic for a seed):

1. Depth range. Where the cameras' optical axes converge (the least-squares point closest to all
   axes lies in front of at least 80 % of the cameras and the fit is well conditioned), D is the
   median distance of the cameras to it and depths span [D / 2, 3 D]. Otherwise (axes parallel
   or diverging: forward-facing) depths span [s, 100 s] with s the scene scale (the cameras'
   spread), the usual depth / baseline ratios of handheld forward-facing captures.
2. Each point takes a training view (round robin), a uniform random pixel of it, a depth uniform
   in log depth over the range (as many points per octave: near and far content alike), and the
   colour of that pixel (a masked pixel: the mean of the view's kept pixels).

A capture is "forward-facing" when its optical axes all lie within 30 degrees of their mean
direction; `looks_forward_facing` tells, and the fit warns when such a capture has no points.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from morphgs.camera import Camera

__all__ = ["depth_range", "looks_forward_facing", "ray_points"]

FORWARD_DEGREES = 30.0


def _axes(cams: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    c2w = np.stack([c.camera_to_world for c in cams])
    return c2w[:, :3, 3], c2w[:, :3, 2]  # centres, forward (+z, OpenCV) axes


def looks_forward_facing(cams: Sequence[Camera]) -> bool:
    """True when every optical axis lies within 30 degrees of the axes' mean direction."""
    if len(cams) < 2:
        return True
    _, z = _axes(cams)
    m = z.mean(axis=0)
    n = np.linalg.norm(m)
    if n < 1e-9:
        return False
    return bool(np.all(z @ (m / n) >= np.cos(np.radians(FORWARD_DEGREES))))


def depth_range(cams: Sequence[Camera], scene_scale: float) -> tuple[float, float, str]:
    """(near, far, how) of the rule in the module docs."""
    c, z = _axes(cams)
    if len(cams) >= 2:
        a = np.zeros((3, 3))
        b = np.zeros(3)
        for ci, zi in zip(c, z):
            p = np.eye(3) - np.outer(zi, zi)
            a += p
            b += p @ ci
        ev = np.linalg.eigvalsh(a)
        if ev[0] > 0.05 * len(cams):  # the axes are not (nearly) parallel
            x = np.linalg.solve(a, b)
            ahead = np.einsum("ij,ij->i", x - c, z) > 0
            if ahead.mean() >= 0.8:
                d = float(np.median(np.linalg.norm(c - x, axis=1)))
                if d > 1e-6:
                    return d / 2, 3 * d, f"axes converge {d:.3g} from the cameras"
    s = max(float(scene_scale), 1e-6)
    return s, 100 * s, f"axes do not converge: {s:.3g}..{100 * s:.3g} (scene scale x 1..100)"


def ray_points(cams: Sequence[Camera], images: Sequence[np.ndarray], n: int, seed: int,
               scene_scale: float, masks: Sequence[np.ndarray | None] | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """(points (n, 3) float32, colours (n, 3) float32 in [0, 1], description). A point on a
    masked pixel takes the mean colour of the view's kept pixels (masked pixels never count)."""
    near, far, how = depth_range(cams, scene_scale)
    rng = np.random.default_rng([int(seed), 0x5EED_0A15])
    v = np.arange(n) % len(cams)
    u01 = rng.random((n, 2))
    t = rng.random(n)
    depth = np.exp(np.log(near) + t * (np.log(far) - np.log(near)))
    pts = np.empty((n, 3))
    cols = np.empty((n, 3))
    for i, (cam, img) in enumerate(zip(cams, images)):
        sel = v == i
        if not sel.any():
            continue
        px = u01[sel, 0] * cam.width
        py = u01[sel, 1] * cam.height
        d = depth[sel]
        xc = np.stack([(px - cam.cx) / cam.fx * d, (py - cam.cy) / cam.fy * d, d], axis=1)
        c2w = cam.camera_to_world
        pts[sel] = xc @ c2w[:3, :3].T + c2w[:3, 3]
        h, w = img.shape[:2]
        iy = np.minimum((py * h / cam.height).astype(int), h - 1)
        ix = np.minimum((px * w / cam.width).astype(int), w - 1)
        col = img[iy, ix].astype(np.float64) / 255.0
        m = masks[i] if masks is not None and i < len(masks) else None
        if m is not None:
            out = ~m[iy, ix]
            col[out] = img[m].mean(axis=0) / 255.0
        cols[sel] = col
    desc = f"random {n} points along the training rays, depths {near:.3g}..{far:.3g} ({how})"
    return pts.astype(np.float32), cols.astype(np.float32), desc
