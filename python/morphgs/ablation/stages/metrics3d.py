"""Stage 7, 3D metrics: 3DGS re-optimised from each refined clip, scored on held-out frames and
against the clean scene's geometry.

- The re-fit: `morphgs fit` of the clip's frames minus the held-out ones (`clips.heldout`, fixed
  indices; neither the refiner's training nor the re-fit sees them), the study's [refit]
  settings, random initialisation, the same seed for every row.
- Appearance: PSNR, SSIM (and LPIPS when its weights are there) of the re-fit's renders at the
  held-out cameras against the clean frames.
- Geometry (ground truth: the clean dense 3DGS, see docs/ablation.md): the re-fit's and the clean
  scene's depth maps at the clip's cameras, unprojected where each render's alpha is >= 0.5
  (the visible surface: floaters behind it do not count), in units of the clean scene's
  bounding-box diagonal; Chamfer distance (mean of accuracy and completeness) and precision /
  recall / F-score at each threshold of `metrics.fscore` (shares of that diagonal).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "depth_points", "make"]

VERSION = 1
IGNORE = ("threads",)
RESUMABLE = True  # the re-fits resume from their checkpoints in refit/

_MAX_POINTS = 20000


def depth_points(depth: np.ndarray, alpha: np.ndarray, cams: Any, *, scale: float) -> np.ndarray:
    """World points of a clip's depth maps where alpha >= 0.5, divided by `scale`, thinned to at
    most 20k points by a fixed stride (deterministic)."""
    from morphgs.metrics import backproject_depth

    pts = [backproject_depth(depth[i], cams[i], mask=alpha[i] >= 0.5) for i in range(len(cams))]
    p = np.concatenate(pts, 0) / scale if pts else np.zeros((0, 3))
    if len(p) > _MAX_POINTS:
        p = p[:: int(np.ceil(len(p) / _MAX_POINTS))]
    return p


def _refit_data(folder: Path, frames: np.ndarray, clean: np.ndarray, cams: Any, held: list[int]) -> None:
    """A posed-image folder of the clip: refined frames, the held-out ones clean (only scored)."""
    from morphgs.curation.sparse import write_data

    imgs = [clean[i] if i in held else frames[i] for i in range(len(cams))]
    write_data(folder, cams, imgs)


def make(work: Path, *, testset_dir: str, refined_dir: str, refit: dict[str, Any], heldout: list[int],
         thresholds: list[float], lpips_note: str | None, lpips_net: str, seed: int, threads: int) -> None:
    import morphgs
    from morphgs import media
    from morphgs import metrics as M
    from morphgs.ablation.stages.common import read_testset, torch_threads
    from morphgs.ablation.stages.common import fit_config
    from morphgs.camera import Cameras
    from morphgs.fit import fit
    from morphgs.fit.run import random_init_on_purpose

    torch_threads(threads)
    ts, rd = Path(testset_dir), Path(refined_dir)
    meta = read_testset(ts)
    diag = float(meta["bbox_diagonal"])
    rows: dict[str, dict[str, Any]] = {}
    for j in meta["clips"]:
        cd = ts / "clips" / j
        cams = Cameras.from_dict(json.loads((cd / "cameras.json").read_text(encoding="utf-8")))
        clean = media.read_clip(cd / "clean")
        frames = media.read_clip(rd / "clips" / j / "frames")
        data = work / "refit" / j / "data"
        if not (data / "transforms.json").is_file():
            _refit_data(data, frames, clean, cams, heldout)
        train = [i for i in range(len(cams)) if i not in heldout]
        with random_init_on_purpose():  # the re-fit protocol starts from random points: no SfM hint
            res = fit(data, work / "refit" / j / "run", config=fit_config(refit, seed), views=train, holdout="none",
                      init="random", progress=False)
        held_cams = Cameras.from_list([cams[i] for i in heldout])
        r_held = morphgs.render(res.scene, held_cams).to_uint8()
        gt_held = clean[heldout]
        row: dict[str, Any] = {
            "psnr3d": float(M.psnr(r_held, gt_held)),
            "ssim3d": float(M.ssim(r_held, gt_held)),
            "lpips3d": None if lpips_note else float(M.lpips(r_held, gt_held, net=lpips_net)),
        }
        r_all = morphgs.render(res.scene, cams)
        pred = depth_points(np.asarray(r_all.depth), np.asarray(r_all.alpha), cams, scale=diag)
        target = depth_points(np.load(cd / "clean_depth.npy"), np.load(cd / "clean_alpha.npy"), cams, scale=diag)
        if len(pred) == 0:  # the re-fit renders nothing opaque: no surface at all
            row.update({"chamfer": None, **{f"f@{t * 100:g}%": 0.0 for t in thresholds}})
        else:
            scores = M.point_cloud_metrics_at(pred, target, thresholds=[float(t) for t in thresholds])
            for t, pc in zip(thresholds, scores):  # one KD-tree pass for every threshold
                row["chamfer"] = pc["chamfer"]
                row[f"f@{t * 100:g}%"] = pc["fscore"]
        rows[j] = row
    (work / "metrics3d.json").write_text(json.dumps({"clips": rows}, indent=1, sort_keys=True) + "\n",
                                         encoding="utf-8")
