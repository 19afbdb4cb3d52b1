"""Posed images for `morphgs fit`: a nerfstudio / DL3DV `transforms.json` or a COLMAP model, each
with its image files, read through `morphgs.trajectory`'s camera readers.

Frames are ordered as the readers order them (by `file_path` / image name, a capture's video
order). Cameras are in the COLMAP world frame (a transforms.json's `applied_transform` is undone,
as `trajectory.from_transforms_json` does), so COLMAP points and splats trained on the same
reconstruction line up with them.

Image sizes: an image must have its camera's size, or be a uniform downscale of it (the
`images_2`, `images_4`, ... folders of DL3DV and Mip-NeRF 360: W/w = H/h up to rounding), in
which case the camera is scaled to the image. Anything else is a `FitDataError` naming the file.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import MorphgsError
from morphgs.camera import Camera, Cameras

__all__ = ["FitDataError", "PosedImages", "load_posed_images"]


class FitDataError(MorphgsError):
    """Posed images that cannot be used: an image whose size disagrees with its camera, an
    unreadable image, a dataset with no cameras (names the file)."""


@dataclass
class PosedImages:
    """Cameras and the image file of each, in capture order.

    Attributes:
        cameras: one camera per image, at the size the file records.
        paths: the image files.
        source: the cameras file or model folder.
        points: a point-cloud file usable as initialisation (COLMAP points3D or the
            transforms.json's `ply_file_path`), or None.
        points_transform: a 4x4 map from the point file's frame to the cameras' frame, or None.
    """

    cameras: Cameras
    paths: list[Path]
    source: str
    points: Path | None = None
    points_transform: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.paths)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.paths]

    def subset(self, indices: list[int]) -> PosedImages:
        return PosedImages(Cameras.from_list([self.cameras[i] for i in indices]),
                           [self.paths[i] for i in indices], self.source, self.points, self.points_transform)

    def load(self, indices: list[int], *, downscale: int = 1) -> tuple[list[np.ndarray], Cameras]:
        """Read images `indices` as uint8 (H, W, 3), with their cameras scaled to the images.

        Args:
            indices: which views.
            downscale: shrink every image by this integer factor (box filter) and its camera
                with it.

        Raises:
            FileNotFoundError: a missing image. FitDataError: an unreadable image or one whose
            size disagrees with its camera.
        """
        from morphgs.media import MediaError, _read_image

        images, cams = [], []
        for i in indices:
            path = self.paths[i]
            if not path.is_file():
                raise FileNotFoundError(f"{path}: image of view {i} is missing (cameras from {self.source})")
            try:
                img = _read_image(path)
            except MediaError as e:
                raise FitDataError(str(e)) from None
            cam = fit_camera_to_image(self.cameras[i], img.shape[1], img.shape[0], path)
            if downscale > 1:
                img, cam = _shrink(img, cam, downscale, path)
            images.append(np.ascontiguousarray(img))
            cams.append(cam)
        return images, Cameras.from_list(cams) if cams else self.cameras[:0]


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


def _from_transforms(path: Path, images: str | None) -> PosedImages:
    from morphgs.trajectory import find_colmap_model, from_transforms_json

    cams = from_transforms_json(path)
    meta = json.loads(path.read_text(encoding="utf-8"))
    frames = sorted((f for f in meta["frames"] if isinstance(f, dict)), key=lambda f: str(f.get("file_path", "")))
    root = path.parent
    paths = []
    for i, fr in enumerate(frames):
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise FitDataError(f"{path}: frames[{i}] has no 'file_path'")
        p = root / images / Path(fp).name if images else root / fp
        # nerfstudio writes some file_paths without their extension
        if not p.suffix and not p.exists():
            for ext in (".png", ".jpg", ".jpeg", ".JPG", ".PNG"):
                if p.with_suffix(ext).exists():
                    p = p.with_suffix(ext)
                    break
        paths.append(p)
    points, transform = None, None
    model = find_colmap_model(root)
    if model is not None and _points3d(model) is not None:
        points = _points3d(model)
    elif isinstance(meta.get("ply_file_path"), str):
        points = root / meta["ply_file_path"]
        if "applied_transform" in meta:
            a = np.vstack([np.asarray(meta["applied_transform"], np.float64).reshape(-1, 4)[:3], [0, 0, 0, 1]])
            transform = np.linalg.inv(a)
    return PosedImages(cams, paths, str(path), points, transform)


def _points3d(model: Path) -> Path | None:
    for name in ("points3D.bin", "points3D.txt"):
        if (model / name).is_file():
            return model / name
    return None


def _from_colmap(model: Path, root: Path, images: str | None) -> PosedImages:
    from morphgs.trajectory import from_colmap
    from morphgs.trajectory.colmap import _read_images_bin, _read_images_txt

    cams = from_colmap(model)
    if (model / "images.bin").is_file() and (model / "cameras.bin").is_file():
        recs = _read_images_bin(model / "images.bin")
    else:
        recs = _read_images_txt(model / "images.txt")
    names = sorted(r[0] for r in recs)
    img_dir = root / (images or "images")
    return PosedImages(cams, [img_dir / n for n in names], str(model), _points3d(model), None)


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
    return {"source": data.source, "names": data.names}
