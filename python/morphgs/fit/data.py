"""Posed images for `morphgs fit`: a nerfstudio / DL3DV `transforms.json` or a COLMAP model, each
with its image files, read through `morphgs.trajectory`'s camera readers.

Frames are ordered as the readers order them (by `file_path` / image name, a capture's video
order). Cameras are in the COLMAP world frame (a transforms.json's `applied_transform` is undone,
as `trajectory.from_transforms_json` does), so COLMAP points and splats trained on the same
reconstruction line up with them.

Every view has its own camera and size (COLMAP's undistorted layout gives every image a slightly
different size; phone captures mix portrait and landscape). Image sizes: an image must have its
camera's size, or be a uniform downscale of it (the `images_2`, `images_4`, ... folders of DL3DV
and Mip-NeRF 360: W/w = H/h up to rounding), in which case the camera is scaled to the image.
Anything else is a `FitDataError` naming the file.

Distorted cameras (COLMAP SIMPLE_RADIAL / RADIAL / OPENCV / FULL_OPENCV, a transforms.json's
k1 k2 k3 p1 p2) are undistorted with OpenCV and cropped to the valid region
(`morphgs.fit.undistort`), cached in the run folder; fisheye models are refused.

Masks (pixels to leave out of the loss and the held-out metrics): a frame's `mask_path` in a
transforms.json, or a `masks/` folder beside the images holding one mask per image (`NAME`,
`NAME.png` or `STEM.png`); zero pixels are ignored, any other value is kept (nerfstudio's and
COLMAP's convention).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.camera import Camera
from morphgs.fit.undistort import Distortion, cached_undistort, colmap_distortion, transforms_distortion
from morphgs.trajectory import CaptureError

__all__ = ["FitDataError", "PosedImages", "load_posed_images"]

MASK_DIR = "masks"


class FitDataError(CaptureError):
    """Posed images that cannot be used: an image whose size disagrees with its camera, an
    unreadable image or mask, a dataset with no cameras (names the file). A CaptureError, hence
    a MorphgsError and a ValueError."""


@dataclass
class PosedImages:
    """Cameras and the image file of each, in capture order.

    Attributes:
        cameras: one camera per image, at the size its cameras file records (the pinhole part
            of a distorted camera).
        paths: the image files.
        source: the cameras file or model folder.
        points: a point-cloud file usable as initialisation (COLMAP points3D or the
            transforms.json's `ply_file_path`), or None.
        points_transform: a 4x4 map from the point file's frame to the cameras' frame, or None.
        distortion: per view, the lens distortion to undo (None: a pinhole camera).
        masks: per view, the mask file (None: every pixel counts).
    """

    cameras: Sequence[Camera]
    paths: list[Path]
    source: str
    points: Path | None = None
    points_transform: np.ndarray | None = field(default=None, repr=False)
    distortion: list[Distortion | None] | None = field(default=None, repr=False)
    masks: list[Path | None] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        n = len(self.paths)
        if len(self.cameras) != n:
            raise FitDataError(f"{self.source}: {len(self.cameras)} cameras for {n} images")
        self.cameras = list(self.cameras)
        if self.distortion is None:
            self.distortion = [None] * n
        if self.masks is None:
            self.masks = [None] * n

    def __len__(self) -> int:
        return len(self.paths)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.paths]

    @property
    def has_masks(self) -> bool:
        return any(m is not None for m in (self.masks or []))

    def subset(self, indices: list[int]) -> PosedImages:
        d, m = self.distortion or [], self.masks or []
        return PosedImages([self.cameras[i] for i in indices], [self.paths[i] for i in indices], self.source,
                           self.points, self.points_transform, [d[i] for i in indices], [m[i] for i in indices])

    def load(self, indices: list[int], *, downscale: int = 1,
             cache: Path | None = None) -> tuple[list[np.ndarray], list[Camera]]:
        """Read images `indices` as uint8 (H, W, 3), with their cameras scaled to the images
        (undistorted, see `read`)."""
        images, cams, _ = self.read(indices, downscale=downscale, cache=cache, masks=False)
        return images, cams

    def read(self, indices: list[int], *, downscale: int = 1, cache: Path | None = None,
             masks: bool = True) -> tuple[list[np.ndarray], list[Camera], list[np.ndarray | None]]:
        """Read images `indices` as uint8 (H, W, 3), their cameras and their masks.

        Args:
            indices: which views.
            downscale: shrink every image by this integer factor (box filter) and its camera
                with it (masks: a pixel is kept when at least half of its block is).
            cache: a folder for undistorted images (the run folder's `undistorted/`); None
                undistorts in memory every time.
            masks: read the masks too (else the list is all None).

        Returns:
            (images, cameras, masks): a mask is a (H, W) bool array, True where the pixel
            counts, or None.

        Raises:
            FileNotFoundError: a missing image or mask. FitDataError: an unreadable image or
            mask, or one whose size disagrees with its camera. CaptureError: a distortion that
            cannot be undone.
        """
        from morphgs.media import MediaError, read_image

        dists, mpaths = self.distortion or [None] * len(self), self.masks or [None] * len(self)
        images, cams, out_masks = [], [], []
        for i in indices:
            path = self.paths[i]
            if not path.is_file():
                raise FileNotFoundError(f"{path}: image of view {i} is missing (cameras from {self.source})")
            try:
                img = read_image(path)
            except MediaError as e:
                raise FitDataError(str(e)) from None
            cam = fit_camera_to_image(self.cameras[i], img.shape[1], img.shape[0], path)
            mask = _read_mask(mpaths[i], img.shape[1], img.shape[0], path) if masks and mpaths[i] is not None else None
            dist = dists[i]
            if dist is not None:
                img_in = img
                img, ucam = cached_undistort(path, lambda: img_in, cam, dist, cache)
                if mask is not None:
                    m8 = mask.astype(np.uint8) * 255
                    mpath = mpaths[i]
                    assert mpath is not None
                    mu, _ = cached_undistort(mpath, lambda: m8, cam, dist, cache, nearest=True, kind="mask")
                    mask = mu > 127
                cam = ucam
            if downscale > 1:
                img, cam2 = _shrink(img, cam, downscale, path)
                if mask is not None:
                    mask = _shrink_mask(mask, cam2.width, cam2.height)
                cam = cam2
            if mask is not None and not mask.any():
                raise FitDataError(f"{mpaths[i]}: the mask of {path.name} leaves no pixel (zero means ignored)")
            images.append(np.ascontiguousarray(img))
            cams.append(cam)
            out_masks.append(None if mask is None or mask.all() else np.ascontiguousarray(mask))
        return images, cams, out_masks


def _read_mask(path: Path | None, width: int, height: int, image: Path) -> np.ndarray:
    """A mask file as (H, W) bool at the image's size (True: the pixel counts)."""
    from PIL import Image, UnidentifiedImageError

    assert path is not None
    if not path.is_file():
        raise FileNotFoundError(f"{path}: mask of {image.name} is missing")
    try:
        with Image.open(path) as im:
            m = im.convert("L")
            if m.size != (width, height):
                w, h = m.size
                if abs(round(w * height / width) - h) > 1:
                    raise FitDataError(f"{path}: mask is {w}x{h}, its image {image.name} is {width}x{height} "
                                       "(not a uniform rescale of it)")
                m = m.resize((width, height), Image.Resampling.NEAREST)
            return np.asarray(m) > 0
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise FitDataError(f"{path}: not a readable mask image ({e})") from None


def _shrink_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    from PIL import Image

    m = Image.fromarray(mask.astype(np.uint8) * 255).resize((width, height), Image.Resampling.BOX)
    return np.asarray(m) >= 128


def fit_camera_to_image(cam: Camera, width: int, height: int, path: Path | str) -> Camera:
    """The camera scaled to an image of `width` x `height` when that is a uniform downscale
    (or upscale) of the camera's size; FitDataError otherwise."""
    if (width, height) == (cam.width, cam.height):
        return cam
    fx, fy = cam.width / width, cam.height / height
    if abs(round(cam.width / fy) - width) <= 1 and abs(round(cam.height / fx) - height) <= 1:
        return cam.resized(width, height)
    raise FitDataError(f"{path}: image is {width}x{height}, but its camera is {cam.width}x{cam.height} "
                       "(not a uniform rescale of it)")


def _shrink(img: np.ndarray, cam: Camera, f: int, path: Path) -> tuple[np.ndarray, Camera]:
    from PIL import Image

    h, w = img.shape[:2]
    nw, nh = max(1, round(w / f)), max(1, round(h / f))
    out = np.asarray(Image.fromarray(img).resize((nw, nh), Image.Resampling.BOX))
    return out, cam.resized(nw, nh)


def _with_ext(p: Path) -> Path:
    # nerfstudio writes some file_paths without their extension
    if not p.suffix and not p.exists():
        for ext in (".png", ".jpg", ".jpeg", ".JPG", ".PNG"):
            if p.with_suffix(ext).exists():
                return p.with_suffix(ext)
    return p


def _mask_folder(root: Path, image_paths: list[Path], source: str) -> list[Path | None] | None:
    """The `masks/` folder's mask of every image (None without a folder); every image needs one."""
    d = root / MASK_DIR
    if not d.is_dir():
        return None
    out: list[Path | None] = []
    for p in image_paths:
        cands = [d / p.name, d / f"{p.name}.png", d / f"{p.stem}.png"]
        found = next((c for c in cands if c.is_file()), None)
        if found is None:
            raise FitDataError(f"{d}: no mask for image {p.name} (looked for {', '.join(c.name for c in cands)}); "
                               f"a {MASK_DIR}/ folder needs one mask per image of {source}")
        out.append(found)
    return out


def _downscaled_folder(root: Path, paths: list[Path]) -> list[Path]:
    """DL3DV's and nerfstudio's layout: transforms.json names `images/...`, but the folder holds
    only the downscaled copies (`images_2/`, `images_4/`, `images_8/`, same file names). When
    every named photo is missing and one such folder has them all, the photos are read from the
    least downscaled one (their cameras are scaled to them as they are read)."""
    if not paths or any(p.exists() for p in paths):
        return paths
    for k in (2, 4, 8):
        d = root / f"images_{k}"
        if d.is_dir():
            cand = [_with_ext(d / p.name) for p in paths]
            if all(c.is_file() for c in cand):
                return cand
    return paths


def _from_transforms(path: Path, images: str | None) -> PosedImages:
    from morphgs.trajectory import find_colmap_model, read_transforms_frames

    frames = read_transforms_frames(path)
    meta = json.loads(path.read_text(encoding="utf-8"))
    root = path.parent
    paths, cams, dists = [], [], []
    masks: list[Path | None] = []
    for i, fr in enumerate(frames):
        fp = fr.entry.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise FitDataError(f"{path}: frames[{i}] has no 'file_path'")
        paths.append(_with_ext(root / images / Path(fp).name if images else root / fp))
        cams.append(fr.camera)
        dists.append(transforms_distortion(fr.camera_model, fr.distortion, f"{path}: frames[{i}] ({fp})"))
        mp = fr.entry.get("mask_path")
        if mp is not None and (not isinstance(mp, str) or not mp):
            raise FitDataError(f"{path}: frames[{i}].mask_path must be a file path, got {mp!r}")
        masks.append(_with_ext(root / mp) if mp else None)
    if images is None:
        paths = _downscaled_folder(root, paths)
    if all(m is None for m in masks):
        masks = _mask_folder(root, paths, str(path)) or masks
    elif any(m is None for m in masks):
        first = next(i for i, m in enumerate(masks) if m is None)
        raise FitDataError(f"{path}: some frames have a 'mask_path' and frames[{first}] has none; give every "
                           "frame a mask (an all-white one keeps every pixel)")
    points, transform = None, None
    model = find_colmap_model(root)
    if model is not None and _points3d(model) is not None:
        points = _points3d(model)
    elif isinstance(meta.get("ply_file_path"), str):
        points = root / meta["ply_file_path"]
        if "applied_transform" in meta:
            a = np.vstack([np.asarray(meta["applied_transform"], np.float64).reshape(-1, 4)[:3], [0, 0, 0, 1]])
            transform = np.linalg.inv(a)
    return PosedImages(cams, paths, str(path), points, transform, dists, masks)


def _points3d(model: Path) -> Path | None:
    for name in ("points3D.bin", "points3D.txt"):
        if (model / name).is_file():
            return model / name
    return None


def _from_colmap(model: Path, root: Path, images: str | None) -> PosedImages:
    from morphgs.trajectory import read_colmap_views

    views = read_colmap_views(model)
    img_dir = root / (images or "images")
    paths = [img_dir / v.name for v in views]
    dists = [colmap_distortion(v.model, v.params, f"{model}: image {v.name} (camera {v.camera_id})") for v in views]
    masks = _mask_folder(root, paths, str(model))
    return PosedImages([v.camera for v in views], paths, str(model), _points3d(model), None, dists, masks)


def load_posed_images(path: str | os.PathLike[str], *, images: str | None = None) -> PosedImages:
    """Cameras and image files of a dataset.

    Args:
        path: a `transforms.json`, a folder holding one, a COLMAP model folder, or a dataset folder
            with a COLMAP model (`sparse/0`, `sparse`, ...) and an `images/` folder.
        images: the image folder to use instead (relative to the dataset folder), e.g.
            "images_4" (file names are kept).

    Raises:
        FileNotFoundError: nothing usable at `path`. MorphgsError: a malformed cameras file.
    """
    from morphgs.trajectory import find_colmap_model

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder")
    if p.is_file():
        if p.suffix.lower() != ".json":
            raise FitDataError(f"{p}: expected a transforms.json or a dataset folder")
        return _from_transforms(p, images)
    if (p / "transforms.json").is_file():
        return _from_transforms(p / "transforms.json", images)
    model = find_colmap_model(p)
    if model is not None:
        root = p
        # a model folder given directly: images live beside its sparse/ parent
        for cand in (p, p.parent, p.parent.parent):
            if (cand / (images or "images")).is_dir():
                root = cand
                break
        return _from_colmap(model, root, images)
    raise FileNotFoundError(f"{p}: no transforms.json and no COLMAP model (cameras + images .bin/.txt) here")


def describe(data: PosedImages) -> dict[str, Any]:
    """A JSON-able identity of the data (for the run's fingerprint)."""
    d: dict[str, Any] = {"source": data.source, "names": data.names}
    if any(x is not None for x in data.distortion or []):
        d["distortion"] = [None if x is None else [x.model, list(x.coeffs)] for x in data.distortion or []]
    if data.has_masks:
        d["masks"] = [None if m is None else str(m) for m in data.masks or []]
    return d
