"""Render Gaussian-splat scenes on the CPU with the semantics of the reference 3DGS rasterizers.

`render(scene, camera)` gives a `Render` holding float32 colour, expected depth and alpha.
The work runs natively, parallel over 16x16 tiles and frames with the GIL released; the output
is bit-identical whatever the thread count (RAYON_NUM_THREADS / MORPHGS_NUM_THREADS).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from morphgs._core import GaussianScene, _render, _write_exr_batch, _write_png_batch
from morphgs.camera import Camera, Cameras

__all__ = ["Render", "RenderBuffers", "render", "render_many"]

CameraLike = Camera | Cameras | Sequence[Camera]


@dataclass(frozen=True)
class Render:
    """The images of one render.

    Attributes:
        rgb: float32 colour, (H,W,3) for a single `Camera`, (F,H,W,3) for `Cameras`.
            Not clipped: values can exceed 1 where SH colours do.
        depth: float32 expected depth D / max(1 - T, 1e-10) (camera z; 0 where nothing is hit),
            (H,W) or (F,H,W).
        alpha: float32 accumulated opacity 1 - T, (H,W) or (F,H,W).
        stats: counts and stage times of the native render: frames, gaussians, visible,
            intersections, evaluations (Gaussian-pixel evaluations), useful_evaluations (those
            with alpha >= 1/255 on a pixel not yet stopped; counted only when the environment
            variable MORPHGS_COUNT_USEFUL=1, else 0, as counting slows the blend), project_s, sort_s, bin_s,
            blend_s (seconds, summed over frames), simd, threads.
    """

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def batched(self) -> bool:
        """True when the render holds a frame axis (it came from `Cameras`)."""
        return self.rgb.ndim == 4

    def _frames(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.batched:
            return self.rgb, self.depth, self.alpha
        return self.rgb[None], self.depth[None], self.alpha[None]

    def __len__(self) -> int:
        return int(self.rgb.shape[0]) if self.batched else 1

    def __getitem__(self, i: int) -> Render:
        """Frame `i` as a single-frame Render (negative indices count from the end)."""
        rgb, depth, alpha = self._frames()
        n = rgb.shape[0]
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for a render of {n} frames")
        return Render(rgb[i], depth[i], alpha[i], self.stats)

    def __iter__(self) -> Iterator[Render]:
        for i in range(len(self)):
            yield self[i]

    def to_uint8(self) -> np.ndarray:
        """Colour as uint8: round(clip(rgb, 0, 1) * 255), same shape as `rgb`."""
        return np.round(np.clip(self.rgb, 0.0, 1.0) * 255.0).astype(np.uint8)

    def save(self, folder: str | os.PathLike[str], *, start: int = 0) -> list[Path]:
        """Write every frame into `folder` (created if missing).

        Frame i is written as `{start+i:05d}.png` (8-bit RGB, see `to_uint8`),
        `{start+i:05d}.depth.exr` and `{start+i:05d}.alpha.exr` (single-channel "Y" float32
        OpenEXR, lossless). Files are written atomically and in parallel.

        Args:
            folder: output directory.
            start: number of the first frame in the file names.

        Returns:
            The paths of the PNG files, in frame order.

        Raises:
            OSError: a file cannot be written.
        """
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        rgb, depth, alpha = self._frames()
        names = [f"{start + i:05d}" for i in range(rgb.shape[0])]
        pngs = [out / f"{n}.png" for n in names]
        # float32 colour: each PNG writer converts its own frame by to_uint8's rule
        img = rgb if rgb.dtype == np.float32 else self.to_uint8().reshape(rgb.shape)
        _write_png_batch(pngs, np.ascontiguousarray(img))
        _write_exr_batch([out / f"{n}.depth.exr" for n in names], np.ascontiguousarray(depth))
        _write_exr_batch([out / f"{n}.alpha.exr" for n in names], np.ascontiguousarray(alpha))
        return pngs


class RenderBuffers:
    """Output memory that `render_many(..., out=buffers)` renders into call after call.

    A render into fresh arrays has the kernel clear every page of them on their first write
    (memory the process just got is zeroed page by page; a 16-frame 832x480 chunk of a pair is
    128 MB). Rendering into memory kept from an earlier call skips that: the renderer writes
    every value, so nothing is cleared. The buffers grow to the largest batch seen.

    `sets` sets of arrays are used in turn, one per call: a Render returned by a call stays valid
    until `sets` more calls render into the same buffers (each set is overwritten when its turn
    comes again). With `sets=2` one chunk can be written to disk by another thread while the
    next is rendered (double buffering).
    """

    def __init__(self, sets: int = 1) -> None:
        if not isinstance(sets, int) or sets < 1:
            raise ValueError(f"sets must be a positive int, got {sets!r}")
        empty = np.empty(0, np.float32)
        self._sets = [[empty, empty, empty] for _ in range(sets)]
        self._next = 0

    def take(self, scenes: int, frames: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The next set as (rgb (S,F,H,W,3), depth (S,F,H,W), alpha (S,F,H,W)) float32 views."""
        arrays = self._sets[self._next]
        self._next = (self._next + 1) % len(self._sets)
        n = scenes * frames * height * width
        if arrays[1].size < n:  # grow (np.empty: the renderer writes every value)
            arrays[:] = [np.empty(3 * n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)]
        shape = (scenes, frames, height, width)
        return arrays[0][: 3 * n].reshape(*shape, 3), arrays[1][:n].reshape(shape), arrays[2][:n].reshape(shape)


def _as_cameras(cameras: CameraLike) -> tuple[Cameras, bool]:
    if isinstance(cameras, Camera):
        return Cameras.from_list([cameras]), False
    if isinstance(cameras, Cameras):
        return cameras, True
    if isinstance(cameras, Sequence) and all(isinstance(c, Camera) for c in cameras):
        return Cameras.from_list(cameras), True
    raise TypeError(f"expected a Camera, Cameras or a list of Camera, got {type(cameras).__name__}")


def _background(background: npt.ArrayLike) -> tuple[float, float, float]:
    bg = np.asarray(background, dtype=np.float64)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValueError(f"background must be 3 finite numbers, got {background!r}")
    return float(bg[0]), float(bg[1]), float(bg[2])


def _check_degree(scenes: Sequence[GaussianScene], sh_degree: int | None) -> None:
    if sh_degree is None:
        return
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
    for s in scenes:
        if sh_degree > s.sh_degree:
            raise ValueError(f"sh_degree {sh_degree} exceeds the scene's SH degree {s.sh_degree}")


def render_many(
    scenes: Sequence[GaussianScene],
    cameras: CameraLike,
    *,
    background: npt.ArrayLike = (0.0, 0.0, 0.0),
    max_alpha: float = 0.99,
    sh_degree: int | None = None,
    antialiased: bool = False,
    out: RenderBuffers | None = None,
) -> list[Render]:
    """Render several scenes along the same cameras in one parallel pass.

    Args:
        scenes: the scenes (e.g. a clean scene and its perturbed copy).
        cameras, background, max_alpha, sh_degree, antialiased: as in `render`.
        out: render into these reusable buffers instead of new arrays (the same values); the
            returned Renders are views of them, overwritten by a later call (see RenderBuffers).

    Returns:
        One Render per scene, shaped as `render` shapes it for `cameras`.

    Raises:
        ValueError: bad options or cameras; sh_degree above a scene's degree.
    """
    scenes = list(scenes)
    if not all(isinstance(s, GaussianScene) for s in scenes):
        raise TypeError("scenes must be GaussianScene objects")
    cams, batched = _as_cameras(cameras)
    _check_degree(scenes, sh_degree)
    if not (0.0 < float(max_alpha) <= 1.0):
        raise ValueError(f"max_alpha must be in (0, 1], got {max_alpha}")
    if out is not None and not isinstance(out, RenderBuffers):
        raise TypeError(f"out must be a RenderBuffers, got {type(out).__name__}")
    arrays = None if out is None else out.take(len(scenes), len(cams), cams.height, cams.width)
    rgb, depth, alpha, stats = _render(
        scenes,
        np.ascontiguousarray(cams.world_to_camera, dtype=np.float64),
        np.ascontiguousarray(cams.K, dtype=np.float64),
        cams.width,
        cams.height,
        near=cams.near,
        far=cams.far,
        background=_background(background),
        max_alpha=float(max_alpha),
        sh_degree=sh_degree,
        antialiased=bool(antialiased),
        out=arrays,
    )
    renders = []
    for s in range(len(scenes)):
        if batched:
            renders.append(Render(rgb[s], depth[s], alpha[s], stats))
        else:
            renders.append(Render(rgb[s, 0], depth[s, 0], alpha[s, 0], stats))
    return renders


def render(
    scene: GaussianScene,
    cameras: CameraLike,
    *,
    background: npt.ArrayLike = (0.0, 0.0, 0.0),
    max_alpha: float = 0.99,
    sh_degree: int | None = None,
    antialiased: bool = False,
) -> Render:
    """Render a scene from one camera or a batch of cameras (SPEC §4, "classic" 3DGS).

    Args:
        scene: the Gaussians.
        cameras: a `Camera` (images (H,W,...)), or `Cameras` / a list of `Camera` sharing one
            image size (images (F,H,W,...)).
        background: RGB colour behind the Gaussians (depth always uses 0).
        max_alpha: per-Gaussian alpha cap; 0.99 as INRIA and gsplat >= 1.6, 0.999 reproduces
            gsplat 1.5.3.
        sh_degree: SH bands to evaluate, 0..scene.sh_degree (at most 3); None uses the scene's
            degree (3 for a degree-4 scene).
        antialiased: gsplat's "antialiased" mode (opacity times the low-pass compensation).

    Returns:
        A `Render` (colour, expected depth, alpha, stats).

    Raises:
        ValueError: sh_degree above the scene's degree, bad background or max_alpha, a camera
            with zero size or non-finite values.
        TypeError: `cameras` is not a Camera, Cameras or list of Camera.
    """
    return render_many(
        [scene],
        cameras,
        background=background,
        max_alpha=max_alpha,
        sh_degree=sh_degree,
        antialiased=antialiased,
    )[0]
