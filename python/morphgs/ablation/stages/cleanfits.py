"""Stage 0, clean fits: per capture given as photos (a folder `morphgs fit` reads, without a scene
file), its clean scene, fitted from every photo but the held-out ones.

- The fit: `morphgs fit` of the capture folder with the study's [clean] settings (the `sparse`
  preset's representation, as the test sets' sparse fits: MCMC, SH degree 1), SfM points when the
  capture has them (else random points along the training rays), every 8th photo held out,
  resumable in `fit/`.
- Its size: the photos shrunk by the largest integer factor that keeps them at least the study's
  capture size (`downscale_for`), so the fit sees what the study renders and no more.
- `cleanfit.json`: the held-out PSNR and SSIM (the clean scene's quality: the report names a
  capture below `clean.min_psnr`), steps, Gaussians, the fit's size (its seconds are in the
  study's timings.json with every stage's).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "downscale_for", "fit_config", "load", "make"]

VERSION = 2  # 2: the downscale compares the longer sides (a portrait capture of a landscape study)
IGNORE: tuple[str, ...] = ()
RESUMABLE = True  # the fit resumes from its checkpoint in fit/
HOLDOUT = "every:8"


def downscale_for(photo: tuple[int, int], size: tuple[int, int]) -> int:
    """The largest integer factor that shrinks a `photo` (W, H) to no less than `size` (W, H)
    on both sides, longer side against longer side (a portrait photo of a landscape study is
    turned, as the captures are), 1 when the photo is already as small."""
    (pl, ps), (sl, ss) = sorted(photo, reverse=True), sorted(size, reverse=True)
    return max(1, min(pl // max(1, sl), ps // max(1, ss)))


def fit_config(clean: dict[str, Any], seed: int) -> Any:
    """The FitConfig of a clean fit: the test sets' sparse-fit representation with the [clean]
    steps and sizes, no intermediate evaluation, no LPIPS (the held-out PSNR/SSIM are the note)."""
    from morphgs.ablation.stages.common import fit_config as sparse_config

    cfg = sparse_config({k: clean[k] for k in ("steps", "random_points", "cap_max")}, seed)
    cfg.output.lpips = "off"
    return cfg


def _photo_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return int(im.size[0]), int(im.size[1])


def make(work: Path, *, capture: str, size: tuple[int, int], clean: dict[str, Any], seed: int) -> None:
    from morphgs.fit import fit, load_posed_images

    posed = load_posed_images(capture)
    photo = _photo_size(posed.paths[0])
    d = downscale_for(photo, (int(size[0]), int(size[1])))
    result = fit(capture, work / "fit", config=fit_config(clean, seed), holdout=HOLDOUT, init="auto", downscale=d,
                 progress=False)
    info = {"photos": len(posed), "train_views": len(result.train_views),
            "heldout_views": len(result.heldout_views), "photo_size": list(photo), "downscale": d,
            "steps": result.steps, "gaussians": result.gaussians, "heldout_psnr": result.heldout_psnr,
            "heldout_ssim": result.heldout_ssim, "ply": str(result.ply.relative_to(work))}
    (work / "cleanfit.json").write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")


def load(path: str | Path) -> dict[str, Any]:
    """A finished clean fit's cleanfit.json, with `ply` made absolute."""
    p = Path(path)
    info: dict[str, Any] = json.loads((p / "cleanfit.json").read_text(encoding="utf-8"))
    info["ply"] = str(p / info["ply"])
    return info
