"""Stage 4, test sets: per (test scene, regime), the sparse reconstruction and its test clips.

- The fit: `morphgs fit` of the capture folder from the regime's views (every K-th capture view
  starting with the first, or N spread evenly), random initialisation (no SfM points: they would
  come from all views), the study's [sparse] settings; resumable in `fit/`.
- The clips: a smooth path through the capture cameras (`trajectory.smooth_path`), cut into
  clips of `frames`; `per_scene` of them spread evenly. Per clip: `corrupted/` (the sparse fit's
  render), `clean/` (the clean scene's render), `clean_depth.npy` and `clean_alpha.npy`, and
  `cameras.json`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "clip_cameras", "fit_config", "make", "regime_views"]

VERSION = 1
IGNORE: tuple[str, ...] = ()
RESUMABLE = True  # the sparse fit resumes from its checkpoint in fit/


def regime_views(n: int, params: dict[str, int]) -> list[int]:
    """The training capture indices of a regime (curation.sparse.split_views's rule)."""
    from morphgs.curation.sparse import split_views

    return split_views(n, params)[0]


def fit_config(settings: dict[str, Any], seed: int) -> Any:
    """The FitConfig of a sparse fit or a re-fit: the `sparse` preset with the study's sizes."""
    from morphgs.fit import FitConfig

    cfg = FitConfig.preset("sparse")
    d = cfg.to_dict()
    d["steps"] = int(settings["steps"])
    d["seed"] = int(seed)
    d["init"]["random_points"] = int(settings["random_points"])
    d["mcmc"]["cap_max"] = int(settings["cap_max"])
    step = max(1, min(500, int(settings["steps"])))
    d["output"].update({"eval_every": 0, "checkpoint_every": step, "preview_every": 0})
    return FitConfig.from_dict(d, source="study")


def clip_cameras(capture: Any, frames: int, per_scene: int) -> list[Any]:
    """`per_scene` test clips of `frames` along the smooth capture path, spread evenly."""
    from morphgs import trajectory

    path = trajectory.smooth_path(capture, max(len(capture), frames))
    clips = trajectory.clips(path, frames)
    pick = sorted({int(i) for i in np.round(np.linspace(0, len(clips) - 1, min(per_scene, len(clips))))})
    return [clips[i] for i in pick]


def make(work: Path, *, capture_dir: str, regime: dict[str, int], sparse: dict[str, Any], frames: int,
         per_scene: int, seed: int) -> None:
    import morphgs
    from morphgs import media
    from morphgs.ablation.stages.captures import load_cameras, load_capture, load_scene
    from morphgs.fit import fit

    cap = Path(capture_dir)
    folder, info = load_capture(cap)
    cams = load_cameras(cap)
    views = regime_views(len(cams), regime)
    result = fit(folder, work / "fit", config=fit_config(sparse, seed), views=views, holdout="none", init="random",
                 progress=False)
    sparse_scene = result.scene
    clean_scene = load_scene(cap)
    clips = []
    for j, cc in enumerate(clip_cameras(cams, frames, per_scene)):
        d = work / "clips" / f"{j:02d}"
        clean = morphgs.render(clean_scene, cc)
        bad = morphgs.render(sparse_scene, cc)
        media.write_frames(d / "clean", clean.to_uint8())
        media.write_frames(d / "corrupted", bad.to_uint8())
        np.save(d / "clean_depth.npy", np.asarray(clean.depth, np.float32))
        np.save(d / "clean_alpha.npy", np.asarray(clean.alpha, np.float32))
        (d / "cameras.json").write_text(json.dumps(cc.to_dict()) + "\n", encoding="utf-8")
        clips.append(f"{j:02d}")
    meta = {"scene": info["scene"], "regime": regime, "train_views": views, "capture_views": len(cams),
            "clips": clips, "bbox_diagonal": info["bbox_diagonal"]}
    (work / "testset.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")

