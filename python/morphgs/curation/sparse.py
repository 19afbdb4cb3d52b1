"""Sparse-view reconstructions for `--config sparse:K` / `sparse-n:N` (docs/curation.md, docs/fit.md).

The corrupted side of such a pair is a real 3DGS reconstruction from few views, rendered along
the pair's path. Per (scene, views, seed, resolution, fit settings) one fit is made and cached:

    OUT/fits/<scene>/<label>-<W>x<H>-seed<S>-<hash>/
        data/transforms.json, data/images/      the training (and scoring) views as fitted
        run/                                    the morphgs fit run folder (resumable)

- The capture: the scene's recorded cameras (transforms.json / COLMAP / INRIA cameras.json, at
  the pair resolution) in capture order; a scene without cameras gets a 96-view 360-degree orbit
  (the built-in synthetic scenes their own room orbit).
- Training views: every K-th capture view starting with the first (the paper's S_K), or N views
  spread evenly (both ends included). Up to 8 other views, spread evenly, are held out to score
  the fit.
- Images: the scene folder's real images when every training view has one, else renders of the
  clean scene from those cameras. Real photos keep their own size and orientation (scaled so
  the longer side is the pair's longer side: a capture mixing portrait and landscape, or
  COLMAP's undistorted layout where every image has its own size, fits as it is) and are
  undistorted with their camera's coefficients (docs/fit.md).
- Initialisation: random points along the training views' rays (`init="random"`,
  `morphgs.fit.rays`; no SfM points: they would come from all views). The fit config is the `sparse` preset (3000 steps, MCMC capped at 300k Gaussians, SH
  degree 1) unless the config says otherwise.

A fit is resumable (its run folder checkpoints) and shared: worker processes take a file lock per
fit, so several pairs and workers reuse one reconstruction.
"""

from __future__ import annotations

import ast
import fcntl
import hashlib
import json
import os
import re
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import MorphgsError, MorphgsWarning
from morphgs.camera import Cameras
from morphgs.reliability import one_line

__all__ = ["capture_cameras", "sparse_scene", "split_views"]

CAPTURE_VIEWS = 96
EVAL_VIEWS = 8
_GL = np.diag([1.0, -1.0, -1.0, 1.0])
_CACHE: dict[str, tuple[Any, dict[str, Any]]] = {}


def capture_cameras(source: Any, scene: Any, recorded: Cameras | None, resolution: tuple[int, int],
                    up: Any = "file") -> Cameras:
    """The cameras a sparse fit picks its views from (see the module docs); `up`: the world up
    of the orbit around a scene file without cameras (a `trajectory.scene_up` rule or a vector)."""
    from morphgs import trajectory

    if recorded is not None:
        return recorded
    if source.builtin is not None:
        from morphgs import synthetic

        o = synthetic.suggested_orbit()
        return trajectory.orbit(o.center, o.radius, o.height - o.center[2], CAPTURE_VIEWS, start_degrees=0.0,
                                arc_degrees=360.0 * (CAPTURE_VIEWS - 1) / CAPTURE_VIEWS, fov_y_degrees=50.0,
                                resolution=resolution)
    return trajectory.for_scene(scene, CAPTURE_VIEWS, resolution=resolution, up=up,
                                arc_degrees=360.0 * (CAPTURE_VIEWS - 1) / CAPTURE_VIEWS)


def split_views(n: int, params: dict[str, Any]) -> tuple[list[int], list[int]]:
    """(training, held-out) capture indices: every K-th or N spread evenly; up to 8 others held
    out, spread evenly."""
    if "every" in params:
        train = list(range(0, n, int(params["every"])))
    else:
        k = int(params["n"])
        train = sorted({int(i) for i in np.round(np.linspace(0, n - 1, min(k, n)))})
    rest = [i for i in range(n) if i not in set(train)]
    if rest:
        held = sorted({rest[int(i)] for i in np.round(np.linspace(0, len(rest) - 1, min(EVAL_VIEWS, len(rest))))})
    else:
        held = []
    return train, held


def _real_images(source: Any, count: int) -> tuple[Any, list[int]] | None:
    """The scene folder's posed photos (a `PosedImages`) and, for each recorded camera in capture
    order, its index among them, when there is one photo per recorded camera.

    A scene folder with transforms.json or a COLMAP model: its photos, in the same order. A
    `morphgs fit` run folder (INRIA cameras.json): the photos of the capture it was fitted from
    (`views.json`'s `source`), matched to cameras.json by image name; None when that capture
    has moved or lacks a photo (the sparse fit then trains on renders of the scene)."""
    from morphgs.fit import load_posed_images

    if source.cameras is None:
        return None
    if source.cameras_kind == "inria":
        return _fit_run_images(Path(source.cameras), count)
    if source.cameras_kind not in ("transforms", "colmap"):
        return None
    try:
        posed = load_posed_images(source.cameras if source.cameras_kind == "transforms" else Path(source.cameras))
    except (OSError, ValueError):
        return None
    if len(posed) != count or not all(p.is_file() for p in posed.paths):
        return None
    return posed, list(range(count))


def _capture_of_run(run: Path) -> tuple[Path, Path] | None:
    """(the file that names it, the capture folder) a model folder was fitted from: `morphgs
    fit`'s views.json `source`, or the INRIA trainer's cfg_args `source_path` (its
    `Namespace(...)` line; a relative one is taken from the folder the trainer ran in, which its
    relative `model_path` gives, else from the model folder's parent or the working directory). None when neither file is there; ValueError when one is but names no
    capture."""
    views = run / "views.json"
    if views.is_file():
        try:
            return views, Path(str(json.loads(views.read_text(encoding="utf-8"))["source"]))
        except (ValueError, KeyError, TypeError) as e:
            raise ValueError(f"{views}: unreadable ({one_line(e)})") from e
    cfg = run / "cfg_args"
    if not cfg.is_file():
        return None
    text = cfg.read_text(encoding="utf-8", errors="replace")
    src = _namespace_str(text, "source_path")
    if src is None:
        raise ValueError(f"{cfg}: no source_path='...' in it")
    if src.is_absolute():
        return cfg, src
    # the trainer ran in the folder that its (relative) model_path leads from to this folder
    bases = [run.parent, Path.cwd()]
    model_path = _namespace_str(text, "model_path")
    if model_path is not None and not model_path.is_absolute():
        parts = [p for p in model_path.parts if p != "."]
        here = run.resolve()
        if parts and here.parts[len(here.parts) - len(parts):] == tuple(parts):
            bases.insert(0, Path(*here.parts[:len(here.parts) - len(parts)]))
    return cfg, next((b / src for b in bases if (b / src).is_dir()), bases[0] / src)


def _namespace_str(text: str, key: str) -> Path | None:
    """The string `key='...'` of a Python `Namespace(...)` repr, as a path, or None."""
    m = re.search(rf"""\b{key}=('(?:[^'\\]|\\.)*'|"(?:[^"\\]|\\.)*")""", text)
    return None if m is None else Path(str(ast.literal_eval(m.group(1))))


def _fit_run_images(cameras_json: Path, count: int) -> tuple[Any, list[int]] | None:
    """(photos, order) of the capture a model folder was fitted from (`morphgs fit`'s run folder
    or the INRIA trainer's output, see `_capture_of_run`), matched to cameras.json by image name.
    None when the folder names no capture, and then silently; None with a MorphgsWarning saying
    why when it names one that cannot be used (damaged file, capture moved, a photo missing)."""
    from morphgs.fit import load_posed_images

    try:
        found = _capture_of_run(cameras_json.parent)
    except (OSError, ValueError) as e:
        _warn_renders(str(e))
        return None
    if found is None:
        return None
    named_in, capture = found
    try:
        names = sorted(str(c["img_name"]) for c in json.loads(cameras_json.read_text(encoding="utf-8")))
        posed = load_posed_images(capture)
    except (OSError, ValueError, KeyError, TypeError) as e:
        _warn_renders(f"{named_in}: the capture it names, {capture}, cannot be read ({one_line(e)})")
        return None
    by_stem: dict[str, int] = {}
    for i, path in enumerate(posed.paths):
        by_stem.setdefault(Path(path).stem, i)
        by_stem.setdefault(Path(path).name, i)
    order = [by_stem.get(n, -1) for n in names]
    missing = [n for n, i in zip(names, order) if i < 0 or not posed.paths[i].is_file()]
    if len(order) != count or missing:
        what = (f"no photo for {len(missing)} of its {len(names)} cameras (first: {missing[0]})" if missing
                else f"{len(names)} cameras in {cameras_json.name}, {count} expected")
        _warn_renders(f"{named_in}: the capture it names, {capture}, has {what}")
        return None
    return posed, order


def _warn_renders(problem: str) -> None:
    warnings.warn(f"{problem}; the sparse fit trains on renders of the scene instead of the capture's photos",
                  MorphgsWarning, stacklevel=5)


def fit_view(img: np.ndarray, cam: Any, width: int, height: int) -> tuple[np.ndarray, Any]:
    """A photo and its camera brought to about `width` x `height` pixels the way
    `trajectory.resize_camera` treats a camera: the photo's own orientation and aspect are kept
    (a portrait photo of a landscape pair stays portrait, scaled so its longer side is the
    pair's longer side), so no photo is stretched; every view keeps its own size."""
    from PIL import Image

    s = max(width, height) / max(cam.width, cam.height)
    w, h = max(1, round(cam.width * s)), max(1, round(cam.height * s))
    if (w, h) == (cam.width, cam.height):
        return img, cam
    out = np.asarray(Image.fromarray(img).resize((w, h), Image.Resampling.LANCZOS))
    return out, cam.resized(w, h)


def _fit_dir(out_dir: Path, job: Any, fit_cfg: dict[str, Any], up: list[float] | None) -> Path:
    """The cache folder of a sparse fit; `up` (the capture orbit's up, None when the views are
    recorded cameras or the built-in room orbit) is part of its key, so another --up fits again."""
    key: dict[str, Any] = {"config": job.config.as_dict(), "fit": fit_cfg, "size": [job.width, job.height],
                           "seed": job.run_seed, "scene": job.source.describe()}
    if up is not None:
        key["up"] = [round(v, 9) for v in up]
    ident = json.dumps(key, sort_keys=True)
    h = hashlib.sha256(ident.encode()).hexdigest()[:10]
    return out_dir / "fits" / job.source.id / f"{job.config.label}-{job.width}x{job.height}-seed{job.run_seed}-{h}"


def write_data(folder: Path, cams: Any, images: list[np.ndarray]) -> None:
    """transforms.json + PNGs; sizes per frame (real photos keep their own)."""
    from morphgs._core import _write_png, _write_png_batch

    (folder / "images").mkdir(parents=True, exist_ok=True)
    names = [f"view_{i:05d}.png" for i in range(len(images))]
    if len({im.shape for im in images}) == 1:
        _write_png_batch([folder / "images" / n for n in names], np.ascontiguousarray(np.stack(images)))
    else:
        for n, im in zip(names, images):
            _write_png(folder / "images" / n, np.ascontiguousarray(im))
    c0 = cams[0]
    frames = [{"file_path": f"images/{n}", "transform_matrix": (c.camera_to_world @ _GL).tolist(),
               "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}
              for n, c in zip(names, cams)]
    meta = {"w": c0.width, "h": c0.height, "frames": frames}
    tmp = folder / ".transforms.json.tmp"
    tmp.write_text(json.dumps(meta), encoding="utf-8")
    os.replace(tmp, folder / "transforms.json")


def views_images(source: Any, scene: Any, cams: Cameras, idx: list[int]) -> tuple[list[np.ndarray], list[Any], str]:
    """(images, their cameras, "images" | "renders"). Real photos keep their own size and
    orientation (scaled to the pair's size, `fit_view`) and are undistorted with their camera
    when it has distortion; renders use the capture cameras."""
    import morphgs

    found = _real_images(source, len(cams))
    if found is not None:
        posed, order = found
        imgs, pcams, _ = posed.read([order[i] for i in idx], masks=False)
        w, h = cams[0].width, cams[0].height
        pairs = [fit_view(im, c, w, h) for im, c in zip(imgs, pcams)]
        return [p[0] for p in pairs], [p[1] for p in pairs], "images"
    sub = Cameras.from_list([cams[i] for i in idx])
    r = morphgs.render(scene, sub)
    return list(r.to_uint8()), list(sub), "renders"


def _cached_result(run: Path) -> tuple[dict[str, Any], Any] | None:
    """(fit.json, scene) of a finished cached fit, or None when it is damaged (with a warning: the
    caller fits it again; fit resumes from its checkpoint when that verifies)."""
    import morphgs

    try:
        summary = json.loads((run / "fit.json").read_text(encoding="utf-8"))
        return summary, morphgs.load(run / summary["ply"])
    except (OSError, ValueError, KeyError, TypeError, MorphgsError) as e:
        warnings.warn(f"cached sparse fit {run} is damaged ({one_line(e)}); fitting it again", MorphgsWarning,
                      stacklevel=3)
        (run / "fit.json").unlink(missing_ok=True)
        return None


def sparse_scene(job: Any, scene: Any, recorded: Cameras | None, out_dir: Path,
                 up: str = "file") -> tuple[Any, dict[str, Any]]:
    """The cached sparse reconstruction of a `sparse` job (fitting it first when needed):
    (GaussianScene, info for the manifest). `up`: the up rule of the capture orbit of a scene
    file without cameras (`trajectory.scene_up`)."""
    from morphgs import trajectory
    from morphgs.fit import FitConfig, FitRunError, fit

    params = dict(job.config.params)
    cfg = FitConfig.preset("sparse")
    overrides = dict(params.get("fit", {}))
    if "steps" in params:
        overrides["steps"] = int(params["steps"])
    if overrides:
        cfg = FitConfig.from_dict({**cfg.to_dict(), **overrides}, source=f"config {job.config.label}")
    cfg.seed = int(job.run_seed)
    orbit_up = None
    if recorded is None and job.source.builtin is None:
        orbit_up = [float(v) for v in trajectory.scene_up(scene, up)[0]]
    folder = _fit_dir(out_dir, job, cfg.to_dict(), orbit_up)
    key = str(folder)
    if key in _CACHE:
        return _CACHE[key]
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one process fits; the others wait and reuse it
        run = folder / "run"
        done = run / "fit.json"
        loaded = _cached_result(run) if done.is_file() else None
        if loaded is None:
            cams = capture_cameras(job.source, scene, recorded, (job.width, job.height),
                                   up=orbit_up if orbit_up is not None else "file")
            train, held = split_views(len(cams), params)
            data = folder / "data"
            if not (data / "transforms.json").is_file():
                order = train + held
                imgs, vcams, kind = views_images(job.source, scene, cams, order)
                write_data(data, vcams, imgs)
                (folder / "views.json").write_text(json.dumps(
                    {"capture_views": len(cams), "train": train, "heldout": held, "images": kind}, indent=1) + "\n")
            nt = len(train)
            print(f"curate: fitting {job.source.id} from {nt} of {len(cams)} views ({job.config.label}, "
                  f"{cfg.steps} steps) -> {run}", file=sys.stderr)
            views, holdout = list(range(nt)), list(range(nt, nt + len(held)))
            try:
                fit(data, run, config=cfg, views=views, holdout=holdout, init="random", progress=False)
            except FitRunError:  # no checkpoint of it verifies: fit it from the start
                fit(data, run, config=cfg, views=views, holdout=holdout, init="random", progress=False,
                    resume=False)
            loaded = _cached_result(run)
            if loaded is None:
                raise MorphgsError(f"sparse fit {run}: its result cannot be read back after fitting")
        summary, result = loaded
        views = json.loads((folder / "views.json").read_text(encoding="utf-8"))
    info = {"dir": str(folder.relative_to(out_dir)), "ply": str((run / summary["ply"]).relative_to(out_dir)),
            "capture_views": views["capture_views"], "train_views": views["train"], "images": views["images"],
            "steps": summary["steps"], "gaussians": summary["gaussians"], "heldout_psnr": summary["heldout_psnr"],
            "heldout_ssim": summary["heldout_ssim"], "heldout_lpips": summary.get("heldout_lpips"),
            "seed": int(job.run_seed)}
    _CACHE.clear()
    _CACHE[key] = (result, info)
    return result, info
