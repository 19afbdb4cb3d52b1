"""Small posed datasets on disk for the fit tests: the built-in synthetic room rendered from an
orbit of cameras, written as a nerfstudio transforms.json + PNGs (or a COLMAP text model)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import morphgs
from morphgs import synthetic, trajectory
from morphgs.camera import Cameras

_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def orbit_cameras(views: int, size: tuple[int, int]) -> Cameras:
    o = synthetic.suggested_orbit()
    return trajectory.orbit(o.center, o.radius, o.height - o.center[2], views, start_degrees=0.0,
                            arc_degrees=360.0 * (views - 1) / views, fov_y_degrees=60.0, resolution=size)


def make_dataset(root: Path, *, views: int = 24, size: tuple[int, int] = (64, 48), gaussians: int = 4000,
                 seed: int = 0, points: int = 0) -> tuple[Path, morphgs.GaussianScene, Cameras]:
    """Write `root/transforms.json` and `root/images/frame_XXXXX.png` (renders of the synthetic
    room); with `points` > 0 also `root/points.ply` (a point cloud of that many scene centres,
    referenced as ply_file_path). Returns (root, scene, cameras)."""
    from PIL import Image

    scene = synthetic.scene(gaussians, sh_degree=1, seed=seed)
    cams = orbit_cameras(views, size)
    imgs = morphgs.render(scene, cams).to_uint8()
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (c, im) in enumerate(zip(cams, imgs)):
        Image.fromarray(im).save(root / "images" / f"frame_{i:05d}.png")
        frames.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": (c.camera_to_world @ _GL).tolist()})
    c0 = cams[0]
    meta = {"fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy, "w": size[0], "h": size[1], "frames": frames}
    if points:
        rng = np.random.default_rng(seed)
        idx = rng.choice(len(scene), size=min(points, len(scene)), replace=False)
        write_point_ply(root / "points.ply", np.asarray(scene.means)[idx],
                        np.clip(np.asarray(scene.colors)[idx], 0, 1))
        meta["ply_file_path"] = "points.ply"
    (root / "transforms.json").write_text(json.dumps(meta), encoding="utf-8")
    return root, scene, cams


def write_point_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """A binary little-endian PLY point cloud: float x y z, uchar red green blue."""
    n = len(xyz)
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    c = np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    rec["red"], rec["green"], rec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
            "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path.write_bytes(head.encode() + rec.tobytes())


def small_config(steps: int = 400, strategy: str = "default", **over: object) -> dict:
    """A fit config dict for tiny scenes: the recipe with its schedule compressed."""
    d: dict = {"steps": steps, "strategy": strategy, "sh_degree": 1, "sh_degree_interval": 100,
               "default": {"refine_start": 50, "refine_every": 50, "reset_every": 200, "refine_stop": max(steps - 50, 0)},
               "mcmc": {"refine_start": 50, "refine_every": 50, "cap_max": 6000},
               "init": {"random_points": 3000},
               "output": {"eval_every": 100, "checkpoint_every": 100, "preview_every": 200, "progress_every": 0.0}}
    d.update(over)
    return d
