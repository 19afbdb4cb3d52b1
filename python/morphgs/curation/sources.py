"""Scene discovery: what `morphgs curate SCENE...` accepts.

A SCENE is a scene file (.ply, .splat, .spz, ...), or a folder holding one plus optional
cameras: `transforms.json` (nerfstudio / DL3DV), a COLMAP model (`sparse/0`, `sparse` or the
folder itself), an INRIA-3DGS `cameras.json`, or a nerfstudio `camera_path.json`. INRIA training
outputs (`point_cloud/iteration_N/point_cloud.ply`, highest N wins) are recognised. With no SCENE
the built-in synthetic sample scenes are used.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import MorphgsError
from morphgs.camera import Camera, Cameras

__all__ = ["SCENE_EXTENSIONS", "SceneSource", "builtin_sources", "discover", "slug"]

SCENE_EXTENSIONS = (".ply", ".splat", ".spz", ".ksplat", ".sog", ".glb", ".gltf")
_PREFERRED = ("point_cloud.ply", "splat.ply", "scene.ply", "splat.splat", "scene.splat")
BUILTIN_GAUSSIANS = 100_000


@dataclass(frozen=True)
class SceneSource:
    """One scene to curate: where its Gaussians and (optionally) its cameras come from."""

    id: str
    path: str | None = None
    cameras: str | None = None
    cameras_kind: str | None = None  # "transforms" | "colmap" | "inria" | "camera_path"
    builtin: dict[str, Any] | None = field(default=None)
    capture: str | None = None  # a folder of photos and cameras without a scene (ablate fits it)

    def describe(self) -> str:
        if self.builtin is not None:
            src = f"built-in synthetic {self.builtin}"
        elif self.capture is not None:
            src = f"capture {self.capture} (photos; its clean scene is fitted)"
        else:
            src = str(self.path)
        cams = f"{self.cameras_kind} cameras {self.cameras}" if self.cameras else "no cameras (orbit)"
        return f"{src}; {cams}"

    def load(self) -> Any:
        """Load the GaussianScene."""
        if self.builtin is not None:
            import morphgs.synthetic as synthetic

            return synthetic.scene(**self.builtin)
        import morphgs

        if self.path is None:
            raise MorphgsError(f"{self.capture}: a capture without a scene file: fit it first "
                               f"(`morphgs fit {self.capture} --out RUN`, then use RUN)")
        return morphgs.load(self.path)

    def load_cameras(self, resolution: tuple[int, int]) -> Cameras | None:
        """The recorded cameras resized to `resolution`, or None when the scene has none."""
        if self.cameras is None:
            return None
        from morphgs import trajectory

        if self.cameras_kind == "transforms":
            return trajectory.from_transforms_json(self.cameras, resolution=resolution)
        if self.cameras_kind == "colmap":
            return trajectory.from_colmap(self.cameras, resolution=resolution)
        if self.cameras_kind == "camera_path":
            return trajectory.from_camera_path(self.cameras, resolution=resolution)
        if self.cameras_kind == "inria":
            return read_inria_cameras(self.cameras, resolution=resolution)
        raise ValueError(f"unknown cameras kind {self.cameras_kind!r}")


def read_inria_cameras(path: str | os.PathLike[str], *, resolution: tuple[int, int] | None) -> Cameras:
    """INRIA 3DGS `cameras.json`: a list of {img_name, width, height, position, rotation, fx, fy}
    where [rotation | position] is the camera-to-world (OpenCV axes). Sorted by img_name. With a
    resolution, cameras of several sizes (a `morphgs fit` run of a real capture) are brought to
    it by `trajectory.resize_camera`.

    Raises:
        CaptureError (a MorphgsError): a malformed file or an invalid camera
        (`trajectory.checks`), naming the file and the camera (index in the file, img_name).
    """
    from morphgs.trajectory import CaptureError, camera_from_c2w, resize_camera, warn_stretch

    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise CaptureError(f"{p}: not valid JSON ({e})") from None
    except UnicodeDecodeError as e:
        raise CaptureError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if not isinstance(data, list) or not data:
        raise CaptureError(f"{p}: expected a non-empty list of cameras")
    order = sorted(range(len(data)),
                   key=lambda i: str(data[i].get("img_name", "")) if isinstance(data[i], dict) else "")
    cams: list[Camera] = []
    for i in order:
        c = data[i]
        name = c.get("img_name") if isinstance(c, dict) else None
        where = f"{p}: camera {i}" + (f" ({name})" if isinstance(name, str) and name else "")
        if not isinstance(c, dict):
            raise CaptureError(f"{where}: expected an object with img_name, width, height, position, rotation, fx, fy")
        missing = [k for k in ("width", "height", "position", "rotation", "fx", "fy") if k not in c]
        if missing:
            raise CaptureError(f"{where}: field(s) {', '.join(missing)} missing")
        try:
            rotation = np.asarray(c["rotation"], dtype=np.float64)
            position = np.asarray(c["position"], dtype=np.float64)
            if rotation.shape != (3, 3) or position.shape != (3,):
                raise ValueError
        except (TypeError, ValueError, OverflowError):
            raise CaptureError(f"{where}: 'rotation' must be 3x3 numbers and 'position' 3 numbers") from None
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rotation, position
        cams.append(camera_from_c2w(where, c2w, fx=c["fx"], fy=c["fy"], width=c["width"], height=c["height"]))
    if resolution:
        warn_stretch(cams, *resolution, str(p))
        cams = [resize_camera(c, *resolution) for c in cams]
    sizes = sorted({(c.width, c.height) for c in cams})
    if len(sizes) > 1:
        shown = ", ".join(f"{w}x{h}" for w, h in sizes[:6])
        raise CaptureError(f"{p}: cameras have {len(sizes)} different image sizes ({shown}); pass a resolution")
    return Cameras.from_list(cams)


def slug(name: str, fallback: str = "scene") -> str:
    """`name` as a file or folder name: every run of characters other than letters, digits, '.',
    '_' and '-' becomes one '-', leading and trailing '-' and '.' dropped (`fallback` if nothing is
    left). The one rule for names morphgs derives from scene, regime and condition names."""
    s = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-.")
    return s or fallback


def scene_file_in(folder: Path) -> Path:
    """The scene file a folder stands for, as `morphgs curate` reads it.

    A SceneSplat .npy folder or an unbundled SOG is itself the scene; a `morphgs fit` or INRIA run
    folder gives its highest `point_cloud/iteration_N/point_cloud.ply`; otherwise its only scene file,
    or a preferred name among several. Raises MorphgsError naming the folder when none fits.
    """
    # folders that are themselves scenes: SceneSplat .npy attributes, an unbundled SOG
    if (folder / "coord.npy").is_file() or (folder / "meta.json").is_file():
        return folder
    its = []
    for d in (folder / "point_cloud").glob("iteration_*"):
        m = re.fullmatch(r"iteration_(\d+)", d.name)
        if m and (d / "point_cloud.ply").is_file():
            its.append((int(m.group(1)), d / "point_cloud.ply"))
    if its:
        return max(its)[1]
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCENE_EXTENSIONS)
    if len(files) == 1:
        return files[0]
    for name in _PREFERRED:
        if (folder / name).is_file():
            return folder / name
    if not files:
        raise MorphgsError(f"{folder}: no scene file ({', '.join(SCENE_EXTENSIONS)}) in this folder")
    raise MorphgsError(f"{folder}: several scene files ({', '.join(p.name for p in files)}); "
                       "pass the one to use")


def _cameras_in(folder: Path) -> tuple[str | None, str | None]:
    from morphgs.trajectory import find_colmap_model

    if (folder / "transforms.json").is_file():
        return str(folder / "transforms.json"), "transforms"
    model = find_colmap_model(folder)
    if model is not None:
        return str(model), "colmap"
    if (folder / "cameras.json").is_file():
        return str(folder / "cameras.json"), "inria"
    if (folder / "camera_path.json").is_file():
        return str(folder / "camera_path.json"), "camera_path"
    return None, None


def _capture_problem(folder: Path) -> str | None:
    """None when a folder holds posed photos (transforms.json or a COLMAP model, and the
    images), else why its cameras do not make a capture."""
    from morphgs.fit.data import load_posed_images

    try:
        posed = load_posed_images(folder)
    except (OSError, ValueError, MorphgsError) as e:
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    if not len(posed) or not any(p.is_file() for p in posed.paths):
        return f"none of the {len(posed)} photos its cameras name is there (e.g. {posed.paths[0] if len(posed) else '-'})"
    return None


def discover(inputs: Sequence[str | os.PathLike[str]], *,
             captures: bool = False) -> tuple[list[SceneSource], list[tuple[str, str]]]:
    """Turn command-line SCENE arguments into sources.

    With `captures`, a folder of posed photos without a scene file (transforms.json or a COLMAP
    model, and its images) is a source too: `SceneSource.capture` names it and `path` is None (its
    clean scene is fitted by the caller, as `morphgs ablate` does). Without it such a folder is a
    problem whose message says to fit it first.

    Returns:
        (sources, problems): problems are (input, message) for inputs that are not usable scenes;
        the caller reports them and goes on with the rest. Scene ids are the file stem (or folder
        name), made filesystem-safe; when two inputs share one, each gets a suffix from a hash of
        its resolved path, so ids do not depend on the order of the inputs.
    """
    found: list[tuple[str, SceneSource]] = []
    problems: list[tuple[str, str]] = []
    for raw in inputs:
        p = Path(raw)
        capture: str | None = None
        try:
            if p.is_dir():
                cams, kind = _cameras_in(p)
                name = p.resolve().name
                try:
                    scene_file: Path | None = scene_file_in(p)
                except MorphgsError as e:
                    if kind not in ("transforms", "colmap"):
                        raise
                    why = _capture_problem(p)
                    if why is not None:
                        raise MorphgsError(f"{e}, and its cameras are not a capture of photos: {why}") from None
                    if not captures:
                        raise MorphgsError(f"{e}; it holds photos and cameras: fit it first (`morphgs fit {p} "
                                           "--out RUN`, then use RUN), or give it to `morphgs ablate`, which "
                                           "fits it") from None
                    scene_file, capture = None, str(p.resolve())
            elif p.is_file():
                scene_file, cams, kind, name = p, None, None, p.stem
            else:
                raise FileNotFoundError(f"{p}: no such file or folder")
        except (OSError, MorphgsError) as e:
            problems.append((str(raw), str(e)))
            continue
        found.append((str(p.resolve()), SceneSource(id=slug(name), path=None if scene_file is None else str(scene_file),
                                                    cameras=cams, cameras_kind=kind, capture=capture)))
    counts: dict[str, int] = {}
    for _, s in found:
        counts[s.id] = counts.get(s.id, 0) + 1
    out: list[SceneSource] = []
    seen: set[str] = set()
    for resolved, s in found:
        if counts[s.id] > 1:
            suffix = hashlib.sha256(resolved.encode()).hexdigest()[:8]
            s = dataclasses.replace(s, id=f"{s.id}-{suffix}")
        if s.id in seen:  # the same input given twice
            continue
        seen.add(s.id)
        out.append(s)
    return out, problems


def builtin_sources(count: int = 2, *, n_gaussians: int = BUILTIN_GAUSSIANS) -> list[SceneSource]:
    """The built-in synthetic sample scenes `sample-0`, `sample-1`, ... (seeded, so reproducible)."""
    return [SceneSource(id=f"sample-{i}", builtin={"n_gaussians": n_gaussians, "sh_degree": 3, "seed": i})
            for i in range(count)]
