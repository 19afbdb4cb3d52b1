"""Pinhole cameras in the OpenCV convention (x right, y down, z forward), as gsplat and COLMAP.

A camera is intrinsics (fx, fy, cx, cy), an image size and a world-to-camera 4x4 matrix
(p_c = R p_w + t). Pixel (i, j) has its centre at (j + 0.5, i + 0.5); cx = W/2 is the centre.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, overload

import numpy as np
import numpy.typing as npt

__all__ = ["Camera", "Cameras"]

# nerfstudio/DL3DV/Blender store OpenGL camera axes (x right, y up, z backward).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _as_matrix(m: npt.ArrayLike, name: str, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or Inf values")
    return a


def _check_size(width: int, height: int) -> tuple[int, int]:
    w, h = int(width), int(height)
    if w != width or h != height or w <= 0 or h <= 0:
        raise ValueError(f"image size must be positive integers, got {width}x{height}")
    return w, h


def _check_intrinsics(fx: float, fy: float, cx: float, cy: float) -> tuple[float, float, float, float]:
    vals = (float(fx), float(fy), float(cx), float(cy))
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"camera intrinsics must be finite, got fx={fx} fy={fy} cx={cx} cy={cy}")
    if vals[0] <= 0 or vals[1] <= 0:
        raise ValueError(f"focal lengths must be positive, got fx={fx} fy={fy}")
    return vals


@dataclass(frozen=True)
class Camera:
    """One pinhole camera (OpenCV axes). `world_to_camera` is a (4,4) float64 matrix."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_camera: np.ndarray = field(repr=False)
    near: float = 0.01
    far: float = 1e10

    def __post_init__(self) -> None:
        fx, fy, cx, cy = _check_intrinsics(self.fx, self.fy, self.cx, self.cy)
        w, h = _check_size(self.width, self.height)
        m = _as_matrix(self.world_to_camera, "world_to_camera", (4, 4)).copy()
        m.setflags(write=False)
        if not (0 < float(self.near) < float(self.far)):
            raise ValueError(f"need 0 < near < far, got near={self.near} far={self.far}")
        for k, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy), ("width", w), ("height", h),
                     ("world_to_camera", m), ("near", float(self.near)), ("far", float(self.far))):
            object.__setattr__(self, k, v)

    # ---- constructors ----
    @classmethod
    def from_c2w(
        cls,
        c2w: npt.ArrayLike,
        *,
        fx: float,
        fy: float | None = None,
        width: int,
        height: int,
        cx: float | None = None,
        cy: float | None = None,
        convention: Literal["opencv", "opengl"] = "opencv",
        near: float = 0.01,
        far: float = 1e10,
    ) -> Camera:
        """From a camera-to-world matrix ((4,4) or (3,4)); "opengl" converts nerfstudio/Blender axes."""
        m = np.asarray(c2w, dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        m = _as_matrix(m, "c2w", (4, 4))
        if convention == "opengl":
            m = m @ _GL_TO_CV
        elif convention != "opencv":
            raise ValueError(f"convention must be 'opencv' or 'opengl', got {convention!r}")
        return cls(
            fx=fx,
            fy=fx if fy is None else fy,
            cx=width / 2 if cx is None else cx,
            cy=height / 2 if cy is None else cy,
            width=width,
            height=height,
            world_to_camera=_invert_rigid(m),
            near=near,
            far=far,
        )

    @classmethod
    def from_fov(
        cls,
        c2w: npt.ArrayLike,
        *,
        fov_y_degrees: float,
        width: int,
        height: int,
        convention: Literal["opencv", "opengl"] = "opencv",
        near: float = 0.01,
        far: float = 1e10,
    ) -> Camera:
        """From a vertical field of view in degrees (square pixels, centred principal point)."""
        if not (0.0 < fov_y_degrees < 180.0):
            raise ValueError(f"fov_y_degrees must be in (0, 180), got {fov_y_degrees}")
        f = 0.5 * height / math.tan(math.radians(fov_y_degrees) / 2)
        return cls.from_c2w(c2w, fx=f, fy=f, width=width, height=height, convention=convention,
                            near=near, far=far)

    @classmethod
    def look_at(
        cls,
        eye: npt.ArrayLike,
        target: npt.ArrayLike,
        up: npt.ArrayLike = (0.0, 0.0, 1.0),
        *,
        fov_y_degrees: float = 50.0,
        width: int = 832,
        height: int = 480,
        near: float = 0.01,
        far: float = 1e10,
    ) -> Camera:
        """A camera at `eye` looking at `target`; `up` is the world's up direction."""
        c2w = look_at_c2w(eye, target, up)
        return cls.from_fov(c2w, fov_y_degrees=fov_y_degrees, width=width, height=height,
                            near=near, far=far)

    # ---- derived ----
    @property
    def K(self) -> np.ndarray:
        """(3,3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def camera_to_world(self) -> np.ndarray:
        return _invert_rigid(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return self.camera_to_world[:3, 3].copy()

    def resized(self, width: int, height: int) -> Camera:
        """The same camera rendering at another resolution: fx, cx scale by W'/W; fy, cy by H'/H."""
        w, h = _check_size(width, height)
        sx, sy = w / self.width, h / self.height
        return Camera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h,
                      self.world_to_camera, self.near, self.far)

    def project(self, points: npt.ArrayLike) -> np.ndarray:
        """Project (N,3) world points to (N,2) pixel coordinates (x right, y down)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pc = p @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        return np.stack([self.fx * pc[:, 0] / pc[:, 2] + self.cx,
                         self.fy * pc[:, 1] / pc[:, 2] + self.cy], axis=1)


def look_at_c2w(eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world matrix for a camera at `eye` looking at `target`."""
    e = np.asarray(eye, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - e
    n = np.linalg.norm(f)
    if not np.isfinite(n) or n == 0:
        raise ValueError("look_at: eye and target must be distinct finite points")
    f /= n
    u = np.asarray(up, dtype=np.float64)
    right = np.cross(f, u)
    rn = np.linalg.norm(right)
    if rn < 1e-9:
        raise ValueError("look_at: the view direction is parallel to `up`")
    right /= rn
    down = np.cross(f, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, f, e
    return c2w


def _invert_rigid(m: np.ndarray) -> np.ndarray:
    r, t = m[:3, :3], m[:3, 3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ t
    return out


class Cameras(Sequence[Camera]):
    """F cameras sharing one image size: world_to_camera (F,4,4) and K (F,3,3), float64."""

    def __init__(
        self,
        *,
        world_to_camera: npt.ArrayLike,
        K: npt.ArrayLike,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 1e10,
    ) -> None:
        w2c = np.asarray(world_to_camera, dtype=np.float64)
        k = np.asarray(K, dtype=np.float64)
        if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
            raise ValueError(f"world_to_camera must have shape (F,4,4), got {w2c.shape}")
        if k.shape != (w2c.shape[0], 3, 3):
            raise ValueError(f"K must have shape ({w2c.shape[0]},3,3), got {k.shape}")
        if not (np.all(np.isfinite(w2c)) and np.all(np.isfinite(k))):
            raise ValueError("cameras hold NaN or Inf values")
        if np.any(k[:, 0, 0] <= 0) or np.any(k[:, 1, 1] <= 0):
            raise ValueError("focal lengths must be positive")
        self.width, self.height = _check_size(width, height)
        if not (0 < near < far):
            raise ValueError(f"need 0 < near < far, got near={near} far={far}")
        self.near, self.far = float(near), float(far)
        self.world_to_camera = np.ascontiguousarray(w2c)
        self.K = np.ascontiguousarray(k)
        self.world_to_camera.setflags(write=False)
        self.K.setflags(write=False)

    @classmethod
    def from_list(cls, cameras: Iterable[Camera]) -> Cameras:
        cams = list(cameras)
        if not cams:
            raise ValueError("Cameras.from_list needs at least one camera")
        w, h = cams[0].width, cams[0].height
        if any((c.width, c.height) != (w, h) for c in cams):
            raise ValueError("all cameras must share one image size")
        return cls(world_to_camera=np.stack([c.world_to_camera for c in cams]),
                   K=np.stack([c.K for c in cams]), width=w, height=h,
                   near=cams[0].near, far=cams[0].far)

    @classmethod
    def from_c2w(
        cls,
        c2w: npt.ArrayLike,
        *,
        K: npt.ArrayLike,
        width: int,
        height: int,
        convention: Literal["opencv", "opengl"] = "opencv",
        near: float = 0.01,
        far: float = 1e10,
    ) -> Cameras:
        """From camera-to-world matrices ((F,4,4) or (F,3,4)) and intrinsics ((3,3) or (F,3,3)).

        "opengl" converts nerfstudio/Blender axes (x right, y up, z backward) to OpenCV.
        """
        m = np.asarray(c2w, dtype=np.float64)
        if m.ndim != 3 or m.shape[1:] not in ((4, 4), (3, 4)):
            raise ValueError(f"c2w must have shape (F,4,4) or (F,3,4), got {m.shape}")
        if m.shape[1] == 3:
            bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (m.shape[0], 1, 4))
            m = np.concatenate([m, bottom], axis=1)
        if not np.all(np.isfinite(m)):
            raise ValueError("c2w holds NaN or Inf values")
        if convention == "opengl":
            m = m @ _GL_TO_CV
        elif convention != "opencv":
            raise ValueError(f"convention must be 'opencv' or 'opengl', got {convention!r}")
        k = np.asarray(K, dtype=np.float64)
        if k.shape == (3, 3):
            k = np.broadcast_to(k, (m.shape[0], 3, 3))
        w2c = np.stack([_invert_rigid(x) for x in m]) if len(m) else np.zeros((0, 4, 4))
        return cls(world_to_camera=w2c, K=k, width=width, height=height, near=near, far=far)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready dict: size, near/far, and per camera K (3x3) and world_to_camera (4x4)."""
        return {
            "convention": "opencv",
            "width": self.width,
            "height": self.height,
            "near": self.near,
            "far": self.far,
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Cameras:
        """Inverse of `to_dict`."""
        try:
            return cls(world_to_camera=d["world_to_camera"], K=d["K"], width=d["width"],
                       height=d["height"], near=d.get("near", 0.01), far=d.get("far", 1e10))
        except KeyError as e:
            raise ValueError(f"cameras dict lacks the field {e.args[0]!r}") from None

    def __len__(self) -> int:
        return int(self.world_to_camera.shape[0])

    @overload
    def __getitem__(self, i: int) -> Camera: ...
    @overload
    def __getitem__(self, i: slice) -> Cameras: ...
    def __getitem__(self, i: int | slice) -> Camera | Cameras:
        if isinstance(i, slice):
            return Cameras(world_to_camera=self.world_to_camera[i], K=self.K[i],
                           width=self.width, height=self.height, near=self.near, far=self.far)
        k = self.K[i]
        return Camera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], self.width, self.height,
                      self.world_to_camera[i], self.near, self.far)

    def __iter__(self) -> Iterator[Camera]:
        for i in range(len(self)):
            yield self[i]

    def resized(self, width: int, height: int) -> Cameras:
        w, h = _check_size(width, height)
        k = self.K.copy()
        k[:, 0, :] *= w / self.width
        k[:, 1, :] *= h / self.height
        return Cameras(world_to_camera=self.world_to_camera, K=k, width=w, height=h,
                       near=self.near, far=self.far)

    @property
    def camera_to_world(self) -> np.ndarray:
        return np.stack([_invert_rigid(m) for m in self.world_to_camera]) if len(self) else np.zeros((0, 4, 4))

    def __repr__(self) -> str:
        return f"Cameras(n={len(self)}, {self.width}x{self.height})"
