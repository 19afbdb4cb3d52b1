"""Stage 1, captures: per scene, the capture cameras and images, as a scene folder
(`<scene id>/` with the scene file, `transforms.json`, `images/`, `cameras.json`) that curate,
fit and the later stages read like any posed scene folder.

- Cameras: the scene's recorded ones (transforms.json / COLMAP / INRIA cameras.json) at the
  study's size; otherwise a 360-degree orbit of `views` views (the built-in rooms their own
  orbit, as `sparse:K` makes it).
- Images: the scene folder's real images when every recorded camera has one, else renders of the
  clean scene (as `sparse:K` does today).
- The scene: the scene file, the built-in room, or for a capture given as photos its clean fit
  (stage 0, `cleanfits`), whose held-out quality `capture.json` keeps (`clean_fit`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "load_cameras", "load_capture", "load_scene", "make"]

VERSION = 2  # 2: cameras of another aspect than the study size are centre-cropped, not stretched
IGNORE: tuple[str, ...] = ()
RESUMABLE = False


def _orbit(source: Any, scene: Any, views: int, size: tuple[int, int], up: str | None) -> Any:
    from morphgs import synthetic, trajectory

    arc = 360.0 * (views - 1) / views
    if source.builtin is not None:
        o = synthetic.suggested_orbit()
        return trajectory.orbit(o.center, o.radius, o.height - o.center[2], views, start_degrees=0.0,
                                arc_degrees=arc, fov_y_degrees=50.0, resolution=size)
    return trajectory.for_scene(scene, views, resolution=size, arc_degrees=arc, up=up or "file")


def make(work: Path, *, source: Any, views: int, size: tuple[int, int], up: str | None,
         clean_dir: str | None) -> None:
    """Write the capture folder of one scene into `work/<scene id>/` (`up`: the orbit's world up
    for a scene file without cameras; None for the built-in rooms, which keep their own orbit;
    `clean_dir`: the clean fit of a capture given as photos, else None)."""
    import morphgs
    from morphgs.ablation.stages import cleanfits
    from morphgs.curation.sparse import views_images, write_data

    folder = work / source.id
    folder.mkdir(parents=True, exist_ok=True)
    fitted = cleanfits.load(clean_dir) if clean_dir is not None else None
    scene = morphgs.load(fitted["ply"]) if fitted is not None else source.load()
    recorded = source.load_cameras(size)
    cams = recorded if recorded is not None else _orbit(source, scene, views, size, up)
    # real photos come with their own cameras (each photo's size and orientation, undistorted);
    # transforms.json pairs every image with its camera, cameras.json keeps the study-size cameras
    images, view_cams, kind = views_images(source, scene, cams, list(range(len(cams))))
    write_data(folder, view_cams, images)
    if source.builtin is not None:
        morphgs.save(scene, folder / "scene.ply")
    elif fitted is not None:
        # relative: the study folder can move (work/ and the finished output sit at the same depth)
        os.symlink(os.path.relpath(Path(fitted["ply"]).resolve(), folder.resolve()), folder / "scene.ply")
    else:
        target = Path(source.path).resolve()
        os.symlink(target, folder / f"scene{''.join(target.suffixes[-2:]) or '.ply'}")
    (folder / "cameras.json").write_text(json.dumps(cams.to_dict()) + "\n", encoding="utf-8")
    lo, hi = (np.asarray(b, np.float64) for b in scene.bounds())
    info = {"scene": source.id, "source": source.describe(), "views": len(cams), "images": kind,
            "bbox_diagonal": float(np.linalg.norm(hi - lo)), "size": list(size)}
    if fitted is not None:
        info["clean_fit"] = {k: fitted[k] for k in ("heldout_psnr", "heldout_ssim", "steps", "gaussians",
                                                    "photos", "heldout_views", "downscale")}
    (work / "capture.json").write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")


def load_capture(path: Path) -> tuple[Path, dict[str, Any]]:
    """(the scene folder, capture.json) of a finished capture stage output."""
    info = json.loads((path / "capture.json").read_text(encoding="utf-8"))
    return path / info["scene"], info


def load_cameras(path: Path) -> Any:
    from morphgs.camera import Cameras

    folder, _ = load_capture(path)
    return Cameras.from_dict(json.loads((folder / "cameras.json").read_text(encoding="utf-8")))


def load_scene(path: Path) -> Any:
    import morphgs

    folder, _ = load_capture(path)
    files = [p for p in folder.iterdir() if p.name.startswith("scene")]
    return morphgs.load(files[0])
