"""The initial Gaussians of a fit (docs/fit.md, "Initialisation").

Specs: `"auto"` (the dataset's points -- COLMAP points3D or a transforms.json's ply_file_path --
when it has them, else random), `"points"` / `"colmap"` (those points, required), `"random"` or
`"random:N"` (N points along the training cameras' rays, at depths derived from the cameras,
each with the colour of its pixel: `morphgs.fit.rays`), `"box"` or `"box:N"` (N points uniform
in the box of the training camera centres, each half-side at least the scene scale, random
colours, from the seeded counter-based generator: the former `random`), `"ply:PATH"`
(a PLY point cloud: x y z and optional red green blue), `"scene:PATH"` (an existing splat scene,
used as it is), or a `GaussianScene`.

From points, Gaussians follow INRIA / gsplat: 3-NN isotropic scales times `init_scale`, identity
rotations, opacity `init_opacity` (0.1 for the default strategy, 0.5 for MCMC), DC colour from
the point colour, higher bands zero.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import GaussianScene, MorphgsError
from morphgs.camera import Camera

from morphgs.fit.config import FitConfig
from morphgs.fit.data import PosedImages

__all__ = ["InitError", "initial_scene"]


class InitError(MorphgsError):
    """An initialisation that cannot be built: no points, an empty cloud or scene."""


def camera_box(centers: np.ndarray, scene_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The box of camera centres, each half-side at least `scene_scale`."""
    lo, hi = centers.min(axis=0), centers.max(axis=0)
    mid, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, scene_scale)
    return mid - half, mid + half


def _from_points(pts: np.ndarray, cols: np.ndarray, cfg: FitConfig, source: str) -> GaussianScene:
    from morphgs import _core

    if len(pts) == 0:
        raise InitError(f"empty initialisation: {source} holds no points")
    ok = np.all(np.isfinite(pts), axis=1)
    pts, cols = pts[ok], cols[ok]
    if len(pts) == 0:
        raise InitError(f"empty initialisation: {source} holds no finite points")
    return _core._fit_init_scene(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(cols, np.float32),
                                 opacity=cfg.init_opacity, scale=cfg.init_scale, sh_degree=cfg.sh_degree)


def initial_scene(init: Any, data: PosedImages, train_centers: np.ndarray, cfg: FitConfig, *,
                  scene_scale: float, train_cameras: Sequence[Camera] | None = None,
                  train_images: Sequence[np.ndarray] | None = None,
                  train_masks: Sequence[np.ndarray | None] | None = None) -> tuple[GaussianScene, str]:
    """The initial scene and a description of where it came from.

    Raises:
        InitError: no points where asked, or an empty cloud or scene. FileNotFoundError: a
        missing file. MorphgsError / SceneFormatError: a malformed file.
    """
    import morphgs
    from morphgs import _core
    from morphgs.fit.points import read_points

    if isinstance(init, GaussianScene):
        if len(init) == 0:
            raise InitError("empty initialisation: the given scene has no Gaussians")
        return init, f"scene object ({len(init)} Gaussians)"
    if not isinstance(init, str):
        raise TypeError(f"init must be a spec string or a GaussianScene, got {type(init).__name__}")
    spec = init.strip()
    if spec == "auto":
        spec = "points" if data.points is not None else "random"
    if spec in ("points", "colmap"):
        if data.points is None:
            raise InitError(f"{data.source}: the dataset has no point cloud (COLMAP points3D or ply_file_path); "
                            "use init='random' or 'ply:PATH'")
        pts, cols = read_points(data.points)
        if data.points_transform is not None and len(pts):
            m = data.points_transform
            pts = (pts.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(np.float32)
        return _from_points(pts, cols, cfg, str(data.points)), f"points {data.points}"
    kind = spec.split(":", 1)[0]
    if kind in ("random", "box") and (spec == kind or spec.startswith(kind + ":")):
        n = cfg.init.random_points
        if ":" in spec:
            try:
                n = int(spec.split(":", 1)[1])
            except ValueError:
                raise InitError(f"init {init!r}: {kind}:N needs an integer N") from None
        if n < 1:
            raise InitError(f"empty initialisation: init {init!r} asks for {n} points")
        if kind == "random" and train_cameras is not None and train_images is not None:
            from morphgs.fit.rays import ray_points

            pts, cols, desc = ray_points(train_cameras, train_images, n, cfg.seed, scene_scale, train_masks)
            return _from_points(pts, cols, cfg, "random"), desc
        lo, hi = camera_box(train_centers, scene_scale)
        pts, cols = _core._fit_random_points(n, [float(v) for v in lo], [float(v) for v in hi], seed=cfg.seed)
        return _from_points(pts, cols, cfg, "random"), f"random {n} points in [{lo.round(3).tolist()}, {hi.round(3).tolist()}]"
    if spec.startswith("ply:"):
        path = Path(spec[4:])
        pts, cols = read_points(path)
        return _from_points(pts, cols, cfg, str(path)), f"point cloud {path}"
    if spec.startswith("scene:"):
        path = Path(spec[6:])
        scene = morphgs.load(path)
        if len(scene) == 0:
            raise InitError(f"empty initialisation: {path} has no Gaussians")
        return scene, f"scene {path}"
    raise InitError(f"init {init!r}: expected auto, points, random[:N], box[:N], ply:PATH or scene:PATH")
