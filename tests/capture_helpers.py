"""Real-capture layouts on disk for the capture tests: COLMAP models (.bin / .txt) whose images
each have their own size and camera model, distorted photos (renders of the synthetic room
warped with OpenCV's lens model), nerfstudio transforms.json with distortion and masks."""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import morphgs
from morphgs import synthetic
from morphgs.camera import Camera
from morphgs.trajectory._rotations import matrix_to_quat

_GL = np.diag([1.0, -1.0, -1.0, 1.0])
MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
             "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6}


@dataclass
class Shot:
    """One photo of a test capture: its name, pinhole camera, COLMAP model and params."""

    name: str
    camera: Camera
    model: str = "PINHOLE"
    params: tuple[float, ...] = ()

    def colmap_params(self) -> tuple[float, ...]:
        c = self.camera
        if self.params:
            return self.params
        if self.model == "SIMPLE_PINHOLE":
            return (c.fx, c.cx, c.cy)
        return (c.fx, c.fy, c.cx, c.cy)


def room(gaussians: int = 3000, seed: int = 0) -> morphgs.GaussianScene:
    return synthetic.scene(gaussians, sh_degree=1, seed=seed)


def orbit_poses(n: int) -> list[np.ndarray]:
    """World-to-camera matrices of n cameras on the room's orbit, looking at its centre."""
    from morphgs.camera import look_at_c2w, _invert_rigid

    o = synthetic.suggested_orbit()
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.asarray(o.center) + np.array([o.radius * np.cos(a), o.radius * np.sin(a), o.height - o.center[2]])
        out.append(_invert_rigid(look_at_c2w(eye, o.center, (0, 0, 1))))
    return out


def pinhole(w2c: np.ndarray, width: int, height: int, fov_y: float = 60.0) -> Camera:
    f = 0.5 * max(width, height) / np.tan(np.radians(fov_y) / 2)
    return Camera(f, f, width / 2, height / 2, width, height, w2c)


def cv_coeffs(model: str, params: tuple[float, ...]) -> np.ndarray:
    if model == "SIMPLE_RADIAL":
        return np.array([params[3], 0, 0, 0], np.float64)
    if model == "RADIAL":
        return np.array([params[3], params[4], 0, 0], np.float64)
    if model == "OPENCV":
        return np.array(params[4:8], np.float64)
    if model == "FULL_OPENCV":
        return np.array(params[4:12], np.float64)
    return np.zeros(4)


def distorted_photo(scene: morphgs.GaussianScene, cam: Camera, coeffs: np.ndarray) -> np.ndarray:
    """What a lens with OpenCV `coeffs` and pinhole part `cam` records: every photo pixel looks
    along the ray its undistorted point gives; colours come from a larger pinhole render."""
    import cv2

    pad = 0.6
    pw, ph = int(cam.width * (1 + 2 * pad)), int(cam.height * (1 + 2 * pad))
    big = Camera(cam.fx, cam.fy, cam.cx + cam.width * pad, cam.cy + cam.height * pad, pw, ph, cam.world_to_camera)
    canvas = np.asarray(morphgs.render(scene, big).rgb)
    canvas = np.rint(np.clip(canvas, 0, 1) * 255).astype(np.uint8)
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pts = np.stack([u.ravel() - 0.5, v.ravel() - 0.5], axis=1).reshape(-1, 1, 2)
    k = cam.K.copy()
    k[0, 2] -= 0.5
    k[1, 2] -= 0.5
    kb = big.K.copy()
    kb[0, 2] -= 0.5
    kb[1, 2] -= 0.5
    und = cv2.undistortPoints(pts, k, coeffs, P=kb).reshape(cam.height, cam.width, 2).astype(np.float32)
    return cv2.remap(canvas, und[..., 0], und[..., 1], cv2.INTER_LINEAR)


def write_colmap(model: Path, shots: list[Shot], *, binary: bool = True,
                 points: np.ndarray | None = None, colors: np.ndarray | None = None) -> Path:
    """cameras / images (/ points3D) in COLMAP's binary or text form, one camera per shot."""
    model.mkdir(parents=True, exist_ok=True)
    quats = [matrix_to_quat(s.camera.world_to_camera[:3, :3]) for s in shots]
    if binary:
        cb = struct.pack("<Q", len(shots))
        for i, s in enumerate(shots):
            ps = s.colmap_params()
            cb += struct.pack("<iiQQ", i + 1, MODEL_IDS[s.model], s.camera.width, s.camera.height)
            cb += struct.pack(f"<{len(ps)}d", *ps)
        (model / "cameras.bin").write_bytes(cb)
        ib = struct.pack("<Q", len(shots))
        for i, (s, q) in enumerate(zip(shots, quats)):
            ib += struct.pack("<i7di", i + 1, *q, *s.camera.world_to_camera[:3, 3], i + 1)
            ib += s.name.encode() + b"\x00" + struct.pack("<Q", 0)
        (model / "images.bin").write_bytes(ib)
        if points is not None:
            pb = struct.pack("<Q", len(points))
            cols = np.rint(np.clip(colors if colors is not None else np.full_like(points, 0.5), 0, 1) * 255)
            for j, (p, c) in enumerate(zip(points, cols.astype(np.uint8))):
                pb += struct.pack("<Q3d3BdQ", j + 1, *p, *c, 0.5, 0)
            (model / "points3D.bin").write_bytes(pb)
    else:
        lines = [f"{i + 1} {s.model} {s.camera.width} {s.camera.height} " + " ".join(repr(float(v)) for v in s.colmap_params())
                 for i, s in enumerate(shots)]
        (model / "cameras.txt").write_text("# cameras\n" + "\n".join(lines) + "\n")
        il = []
        for i, (s, q) in enumerate(zip(shots, quats)):
            t = s.camera.world_to_camera[:3, 3]
            il.append(f"{i + 1} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {i + 1} {s.name}")
            il.append("")
        (model / "images.txt").write_text("# images\n" + "\n".join(il) + "\n")
    return model


def write_capture(root: Path, scene: morphgs.GaussianScene, shots: list[Shot], *, binary: bool = True,
                  points: int = 0) -> Path:
    """A COLMAP dataset folder: `images/` (each photo rendered at its own camera, distorted by its
    model) and `sparse/0`."""
    from PIL import Image

    (root / "images").mkdir(parents=True, exist_ok=True)
    for s in shots:
        coeffs = cv_coeffs(s.model, s.colmap_params())
        if np.any(coeffs != 0):
            img = distorted_photo(scene, s.camera, coeffs)
        else:
            img = render_u8(scene, s.camera)
        Image.fromarray(img).save(root / "images" / s.name)
    pts = cols = None
    if points:
        rng = np.random.default_rng(0)
        idx = rng.choice(len(scene), size=min(points, len(scene)), replace=False)
        pts, cols = np.asarray(scene.means, np.float64)[idx], np.asarray(scene.colors)[idx]
    write_colmap(root / "sparse" / "0", shots, binary=binary, points=pts, colors=cols)
    return root


def write_transforms(root: Path, scene: morphgs.GaussianScene, cams: list[Camera], *,
                     distortion: dict[str, float] | None = None, masks: list[np.ndarray] | None = None,
                     extra: dict | None = None) -> Path:
    """A nerfstudio capture: transforms.json with per-frame intrinsics and sizes, photos (warped by
    `distortion`, OpenCV k1 k2 p1 p2 [k3]) and optional masks (`mask_path`)."""
    from PIL import Image

    (root / "images").mkdir(parents=True, exist_ok=True)
    d = distortion or {}
    coeffs = np.array([d.get("k1", 0), d.get("k2", 0), d.get("p1", 0), d.get("p2", 0), d.get("k3", 0)], np.float64)
    frames = []
    for i, c in enumerate(cams):
        name = f"images/frame_{i:05d}.png"
        if np.any(coeffs != 0):
            img = distorted_photo(scene, c, coeffs)
        else:
            img = render_u8(scene, c)
        Image.fromarray(img).save(root / name)
        fr = {"file_path": name, "transform_matrix": (c.camera_to_world @ _GL).tolist(), "fl_x": c.fx,
              "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}
        if masks is not None:
            (root / "masks").mkdir(exist_ok=True)
            Image.fromarray(masks[i].astype(np.uint8) * 255).save(root / f"masks/frame_{i:05d}.png")
            fr["mask_path"] = f"masks/frame_{i:05d}.png"
        frames.append(fr)
    meta = {"camera_model": "OPENCV", **d, "frames": frames, **(extra or {})}
    (root / "transforms.json").write_text(json.dumps(meta), encoding="utf-8")
    return root


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (a.astype(np.float64) - b.astype(np.float64)) / 255.0
    if mask is not None:
        d = d[mask]
    return float(-10 * np.log10(np.mean(d ** 2) + 1e-12))


def render_u8(scene: morphgs.GaussianScene, cam: Camera) -> np.ndarray:
    return np.rint(np.clip(np.asarray(morphgs.render(scene, cam).rgb), 0, 1) * 255).astype(np.uint8)


def forward_facing_cameras(size: tuple[int, int] = (64, 48), grid: tuple[int, int] = (5, 4),
                           spacing: float = 0.12) -> list[Camera]:
    """An LLFF-style capture of the room: cameras on a small grid, every one looking the same way
    (at the room's centre from the orbit's first position)."""
    from morphgs.camera import _invert_rigid, look_at_c2w

    o = synthetic.suggested_orbit()
    c0 = np.asarray(o.center, float)
    eye0 = c0 + np.array([o.radius, 0, o.height - c0[2]])
    fwd = (c0 - eye0) / np.linalg.norm(c0 - eye0)
    right = np.cross(fwd, [0, 0, 1])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    b = spacing * o.radius
    w, h = size
    f = 0.5 * w / np.tan(np.radians(30))
    cams = []
    for j in range(grid[1]):
        for i in range(grid[0]):
            e = eye0 + right * (i - (grid[0] - 1) / 2) * b + up * (j - (grid[1] - 1) / 2) * b
            cams.append(Camera(f, f, w / 2, h / 2, w, h, _invert_rigid(look_at_c2w(e, e + fwd, (0, 0, 1)))))
    return cams
