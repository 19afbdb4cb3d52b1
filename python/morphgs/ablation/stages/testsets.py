"""Stage 4, test sets: per (test scene, regime), the sparse reconstruction and its test clips.

- The fit: `morphgs fit` of the capture folder from the regime's views (every K-th capture view
  starting with the first, or N spread evenly), random initialisation (no SfM points: they would
  come from all views), the study's [sparse] settings; resumable in `fit/`. Up to 16 of the other
  capture views are held out and scored 8 times along the fit (`testset.json`'s `convergence`:
  the held-out PSNR by step and its change over the last quarter; the report's notes give it per
  regime, so a fit length that leaves the fits rising shows).
- The clips: a smooth path through the capture cameras (`trajectory.smooth_path`); `per_scene`
  windows of `frames` consecutive frames, one per equal run of the path, each the window farthest
  from the regime's training cameras (novel views: `novel_windows`). Per clip: `corrupted/` (the
  sparse fit's render), `clean/` (the clean scene's render), `clean_depth.npy` and
  `clean_alpha.npy`, and `cameras.json`.
- A capture of real photos: the clips are runs of `frames` consecutive photos along the real camera
  sequence (video order, or a nearest-neighbour path when the photos have none: `trajectory.camera_sequence`),
  as far from the training photos as the sequence allows, and `clean/` holds the photos themselves,
  so the 2D metrics and the re-fit's held-out frames are scored against real pixels; the depth and alpha stay the clean fit's (the geometry's reference).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.ablation.stages.common import fit_config

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "clip_cameras", "convergence", "fit_config", "make", "novel_windows",
           "photo_clips", "regime_views"]

VERSION = 4  # 2: clips of real photos along the capture; 3: the sparse fit's convergence (held-out views);
# 4: clips of novel views (the windows farthest from the training cameras), a rendered clip's start recorded
IGNORE: tuple[str, ...] = ()
RESUMABLE = True  # the sparse fit resumes from its checkpoint in fit/


def regime_views(n: int, params: dict[str, int]) -> list[int]:
    """The training capture indices of a regime (curation.sparse.split_views's rule)."""
    from morphgs.curation.sparse import split_views

    return split_views(n, params)[0]


def novel_windows(centers: np.ndarray, train: np.ndarray, frames: int, per_scene: int) -> list[int]:
    """The first cameras of `per_scene` test clips of `frames` consecutive cameras along a path
    (`centers`, in path order), of views as novel as the path allows: the windows are cut into
    `per_scene` equal runs and each run gives the window whose camera nearest a training camera
    (`train`, centres) is the farthest; on a tie (every window holds a training camera, as a
    16-photo run does at S8) the one holding the fewest, then the earliest.

    A clip through a training view would score that frame at the fit's own reproduction (44-54
    dB on the toy rooms against 11-14 dB between views), where a refiner can only lose: one such
    frame moved a 16-frame clip's mean PSNR by 2-2.5 dB and made every refiner look worse than
    its input (docs/ablation.md, "Test clips of novel views")."""
    n = len(centers) - frames + 1
    if n < 1:
        return []
    if len(train):
        near = np.min(np.linalg.norm(centers[:, None, :] - train[None, :, :], axis=-1), axis=1)
    else:
        near = np.full(len(centers), np.inf)
    far = np.array([near[s:s + frames].min() for s in range(n)])
    held = np.array([np.count_nonzero(near[s:s + frames] == 0.0) for s in range(n)])
    out = []
    for part in np.array_split(np.arange(n), min(per_scene, n)):
        best = max(part, key=lambda s: (far[s], -held[s], -s))
        out.append(int(best))
    return out


def clip_cameras(capture: Any, frames: int, per_scene: int, train_views: list[int]) -> tuple[list[Any], list[int]]:
    """`per_scene` test clips of `frames` along the smooth capture path, of novel views
    (`novel_windows` from the capture cameras `train_views`): (clips, their first path frames)."""
    from morphgs import trajectory

    path = trajectory.smooth_path(capture, max(len(capture), frames))
    train = np.stack([capture[i].center for i in train_views]) if train_views else np.zeros((0, 3))
    starts = novel_windows(np.stack([c.center for c in path]), train, frames, per_scene)
    return [path[s:s + frames] for s in starts], starts


CONVERGENCE_VIEWS = 16


def convergence(eval_csv: Path, steps: int, heldout: list[int]) -> dict[str, Any]:
    """The sparse fit's held-out PSNR along its steps (from its eval.csv) and the change over its
    last quarter: how far from converged the fit length leaves it."""
    import csv

    curve: list[list[float]] = []
    if eval_csv.is_file():
        with open(eval_csv, encoding="utf-8") as f:
            curve = [[int(r["step"]), round(float(r["psnr"]), 4)] for r in csv.DictReader(f) if r.get("psnr")]
    late = [p for s, p in curve if s >= 0.75 * steps]
    gain = round(late[-1] - late[0], 4) if len(late) >= 2 else None
    return {"steps": steps, "heldout_views": heldout, "psnr_by_step": curve, "last_quarter_gain_db": gain}


def photo_clips(folder: Path, frames: int, per_scene: int,
                train_views: list[int]) -> list[tuple[list[int], list[np.ndarray], Any]]:
    """Test clips along the real camera sequence of a capture whose views are photos: `per_scene`
    runs of `frames` consecutive views (`trajectory.camera_sequence`) as far from the training
    photos `train_views` as the sequence allows (`novel_windows`); per clip (view indices,
    photos, their cameras). Photos of another size than the capture's most common one (a pixel
    off, as undistorted photos are) are resized to it with their cameras, so a clip stacks."""
    from collections import Counter

    from PIL import Image

    from morphgs.camera import Cameras
    from morphgs.fit import load_posed_images
    from morphgs.trajectory import camera_sequence

    posed = load_posed_images(folder)
    centers = np.stack([c.center for c in posed.cameras])
    order = camera_sequence(centers)
    train = centers[train_views] if train_views else np.zeros((0, 3))
    (w, h), _ = Counter((c.width, c.height) for c in posed.cameras).most_common(1)[0]
    out = []
    for s in novel_windows(centers[order], train, frames, per_scene):
        idx = order[s:s + frames]
        imgs, cams = posed.load(idx)
        for k, (im, cam) in enumerate(zip(imgs, cams)):
            if (cam.width, cam.height) != (w, h):
                imgs[k] = np.asarray(Image.fromarray(im).resize((w, h), Image.Resampling.LANCZOS))
                cams[k] = cam.resized(w, h)
        out.append((idx, imgs, Cameras.from_list(cams)))
    return out


def make(work: Path, *, capture_dir: str, regime: dict[str, int], sparse: dict[str, Any], frames: int,
         per_scene: int, seed: int) -> None:
    import morphgs
    from morphgs import media
    from morphgs.ablation.stages.captures import load_cameras, load_capture, load_scene
    from morphgs.fit import fit
    from morphgs.fit.run import random_init_on_purpose

    cap = Path(capture_dir)
    folder, info = load_capture(cap)
    cams = load_cameras(cap)
    views = regime_views(len(cams), regime)
    # held-out capture views (up to 16 of those it does not train on), scored 8 times along the fit:
    # its convergence, reported (they never train, so the fit's bytes are those of holdout "none")
    others = sorted(set(range(len(cams))) - set(views))
    held = sorted({others[int(k)] for k in np.round(np.linspace(0, len(others) - 1, min(CONVERGENCE_VIEWS,
                                                                                          len(others))))}) if others else []
    cfg = fit_config(sparse, seed)
    cfg.output.eval_every = max(1, int(sparse["steps"]) // 8) if held else 0
    cfg.output.lpips = "off"
    with random_init_on_purpose():  # a sparse fit from random points by design: no SfM hint
        result = fit(folder, work / "fit", config=cfg, views=views, holdout=held or "none", init="random",
                     progress=False)
    sparse_scene = result.scene
    clean_scene = load_scene(cap)
    runs: list[tuple[list[int] | None, list[np.ndarray] | None, Any]]
    if info["images"] == "images":  # real photos: the clips follow the capture, the photos are the clean frames
        runs = [(idx, imgs, cc) for idx, imgs, cc in photo_clips(folder, frames, per_scene, views)]
    else:
        chosen, starts = clip_cameras(cams, frames, per_scene, views)
        runs = [(None, None, cc) for cc in chosen]
    clips, clip_views = [], []
    for j, (idx, photos, cc) in enumerate(runs):
        d = work / "clips" / f"{j:02d}"
        clean = morphgs.render(clean_scene, cc)
        bad = morphgs.render(sparse_scene, cc)
        media.write_frames(d / "clean", clean.to_uint8() if photos is None else np.stack(photos))
        media.write_frames(d / "corrupted", bad.to_uint8())
        np.save(d / "clean_depth.npy", np.asarray(clean.depth, np.float32))
        np.save(d / "clean_alpha.npy", np.asarray(clean.alpha, np.float32))
        (d / "cameras.json").write_text(json.dumps(cc.to_dict()) + "\n", encoding="utf-8")
        clips.append(f"{j:02d}")
        clip_views.append(idx)
    meta = {"scene": info["scene"], "regime": regime, "train_views": views, "capture_views": len(cams),
            "convergence": convergence(work / "fit" / "eval.csv", int(sparse["steps"]), held),
            "clips": clips, "bbox_diagonal": info["bbox_diagonal"],
            "clean": "photos" if info["images"] == "images" else "renders"}
    if info["images"] == "images":
        meta["clip_views"] = clip_views  # the capture views (photos) of each clip, in order
    else:
        meta["clip_starts"] = starts  # each clip's first frame on the smooth capture path
    (work / "testset.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")

