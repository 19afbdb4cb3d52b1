"""What a real-fit config's reconstruction sees (`sparse:K`, `sparse-n:N`, `underfit:F`,
`cross:P`; docs/curation.md, docs/fit.md): its capture, its training and held-out views, their
images, and the pair path of a `cross` config. The fits themselves, cached and shared, are made
by `morphgs.curation.fits`.

- The capture: the scene's recorded cameras (transforms.json / COLMAP / INRIA cameras.json, at
  the pair resolution) in capture order; a scene without cameras gets a 96-view 360-degree orbit
  (the built-in synthetic scenes their own room orbit).
- Training views (`split_views`): every K-th capture view starting with the first (the paper's
  S_K), or N views spread evenly (both ends included), with up to 8 other views, spread evenly,
  held out to score the fit; for `underfit`, every view but min(8, n // 8) held-out ones; for
  `cross`, the first round(P x n) views, up to 8 of the rest held out.
- Images: the scene folder's real images when every training view has one, else renders of the
  clean scene from those cameras. Real photos keep their own size and orientation (scaled so
  the longer side is the pair's longer side: a capture mixing portrait and landscape, or
  COLMAP's undistorted layout where every image has its own size, fits as it is) and are
  undistorted with their camera's coefficients (docs/fit.md).
- Initialisation: random points along the training views' rays (`init="random"`,
  `morphgs.fit.rays`; no SfM points: they would come from all views). The fit config is the
  `sparse` preset (3000 steps, MCMC capped at 300k Gaussians, SH degree 1) unless the config
  says otherwise.
"""

from __future__ import annotations

import ast
import json
import os
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import MorphgsError, MorphgsWarning
from morphgs.camera import Cameras
from morphgs.reliability import one_line

__all__ = ["capture_cameras", "capture_for", "check_split", "cross_cut", "cross_path", "split_views", "views_images",
           "write_data"]

CAPTURE_VIEWS = 96
EVAL_VIEWS = 8
_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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


def split_views(n: int, params: dict[str, Any], kind: str = "sparse") -> tuple[list[int], list[int]]:
    """(training, held-out) capture indices of a fit config (`kind`, its `params`):

    - "sparse": every K-th ("every") or N spread evenly ("n"); up to 8 others held out, spread
      evenly;
    - "underfit": min(8, n // 8) views held out, at the centres of as many equal parts of the
      capture (never its first or last view), every other view trains;
    - "cross": the first round(P x n) views ("fraction" P) train; up to 8 of the rest, spread
      evenly, are held out (they score the fit where its pairs are rendered).
    """
    if kind == "underfit":
        k = min(EVAL_VIEWS, n // 8)  # at most one view in 8 held out: a short capture keeps 7/8
        held = sorted({int((j + 0.5) * n / k) for j in range(k)})
        return [i for i in range(n) if i not in set(held)], held
    if kind == "cross":
        cut = cross_cut(n, params)
        return list(range(cut)), _spread(list(range(cut, n)))
    if "every" in params:
        train = list(range(0, n, int(params["every"])))
    else:
        k = int(params["n"])
        train = sorted({int(i) for i in np.round(np.linspace(0, n - 1, min(k, n)))})
    return train, _spread([i for i in range(n) if i not in set(train)])


def _spread(views: list[int]) -> list[int]:
    """Up to `EVAL_VIEWS` of `views`, spread evenly (both ends included)."""
    if not views:
        return []
    return sorted({views[int(i)] for i in np.round(np.linspace(0, len(views) - 1, min(EVAL_VIEWS, len(views))))})


def cross_cut(n: int, params: dict[str, Any]) -> int:
    """How many capture views (the first ones) a `cross` fit trains on: round(P x n)."""
    return int(round(float(params["fraction"]) * n))


def check_split(label: str, kind: str, n: int, params: dict[str, Any], min_train: int = 1) -> None:
    """MorphgsError naming the config when its split of `n` capture views leaves fewer than
    `min_train` training views, or (cross) fewer than 2 views to render its pairs along."""
    train, _ = split_views(n, params, kind)
    if len(train) < min_train:
        raise MorphgsError(f"config {label}: leaves {len(train)} training view(s) of {n} capture views "
                           f"(at least {min_train} needed)")
    if kind == "cross" and n - len(train) < 2:
        raise MorphgsError(f"config {label}: 'fraction' {params['fraction']:g} leaves {n - len(train)} of {n} capture "
                           "views to render its pairs along (at least 2 needed)")


def capture_for(job: Any, scene: Any, recorded: Cameras | None, up: Any) -> tuple[Cameras, list[float] | None]:
    """(the capture a fit of `job` picks its views from, the up of its orbit: None when the views
    are recorded cameras or the built-in room orbit); `up`: the --up rule."""
    from morphgs import trajectory

    orbit_up = None
    if recorded is None and job.source.builtin is None:
        orbit_up = [float(v) for v in trajectory.scene_up(scene, up)[0]]
    cams = capture_cameras(job.source, scene, recorded, (job.width, job.height),
                           up=orbit_up if orbit_up is not None else "file")
    return cams, orbit_up


def cross_path(job: Any, scene: Any, recorded: Cameras | None, opts: Any) -> Cameras:
    """The camera path of a `cross` pair: a smooth constant-speed path through the capture views
    the fit did not train on (capture order, as many frames as those views, at least the pair's),
    cut into clips of the pair's frames every `opts.stride`; pair k takes clip k mod #clips. Its
    ends are capture views of that part, so no frame lies among the training views."""
    from morphgs import trajectory

    cams, _ = capture_for(job, scene, recorded, opts.up)
    check_split(job.config.label, "cross", len(cams), job.config.params)
    rest = cams[cross_cut(len(cams), job.config.params):]
    path = trajectory.smooth_path(rest, max(len(rest), job.frames))
    cl = trajectory.clips(path, job.frames, stride=opts.stride)
    return cl[job.index % len(cl)]


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
