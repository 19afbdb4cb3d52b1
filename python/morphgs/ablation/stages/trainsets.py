"""Stage 2, training sets: `curate` of one condition on the training scenes' capture folders
(every scene in the train split), plus the condition's severity: the PSNR of its own pairs
(corrupted vs clean), printed in the table's rows so a severity mismatch shows.

A target condition is `{"kind": "sparse", "every": K}` (or "n"): pairs whose corrupted side is a
sparse fit of the training scene, with the study's sparse-fit settings. A calibrated condition
(`calibrated:FAMILY-S_K`) is curated with the strength distribution its calibration stage wrote
(`stages/calibration.py`): each pair draws its strength from it, seeded.

With `conditions.clean = "photo"` (captures of photos), every pair is a run of consecutive photos
and its clean side is the photos (`curate --trajectory photos`): the refiner learns to map the
corrupted render to real pixels, the scene's own error included.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["IGNORE", "KERNELS", "RESUMABLE", "VERSION", "calibrated_spec", "condition_spec", "key_of", "link_fits", "make",
           "severity"]

VERSION = 1
IGNORE: tuple[str, ...] = ()
RESUMABLE = True  # curate resumes in its output folder (a target's sparse fits are the long part)


def condition_spec(name: str, *, blur_sigma: float, regime: dict[str, int] | None, sparse: dict[str, Any]) -> Any:
    """The curate ConfigSpec of a condition (a target: a sparse config with the study's fit)."""
    from morphgs.curation.plan import ConfigSpec, parse_config

    if regime is None:
        return parse_config(name, blur_sigma=blur_sigma)
    fit = {"init": {"random_points": int(sparse["random_points"])}, "mcmc": {"cap_max": int(sparse["cap_max"])}}
    return ConfigSpec(name, "sparse", {**regime, "steps": int(sparse["steps"]), "fit": fit})


#: Ops whose bytes changed since studies were first cached, and their implementation's version: a
#: training set that uses one carries it in its key (so only those rebuild). shatter 2: the Rust kernel;
#: 3: fragments whose footprint reaches another training view from outside its image dropped. haze 2:
#: its Gaussians flattened as the measured ones are (sheets, not needles); 3: the Rust kernel.
KERNELS: dict[str, int] = {"shatter": 3, "haze": 3}


def key_of(spec: Any) -> dict[str, Any]:
    """The cache key document of a curate ConfigSpec: its dict, plus the version of each op in
    `KERNELS` it uses."""
    doc = spec.as_dict()
    used = {op: v for op, v in KERNELS.items() if op in (doc.get("ops") or {})}
    return {**doc, "kernels": used} if used else doc


def calibrated_spec(name: str, calibration_dir: str | Path) -> Any:
    """The curate ConfigSpec of a calibrated condition: the calibration stage's config.json,
    labelled by the condition's folder-safe name."""
    import dataclasses

    from morphgs.ablation.stages.calibration import CONFIG
    from morphgs.curation.plan import parse_config

    spec = parse_config(str(Path(calibration_dir) / CONFIG))
    return dataclasses.replace(spec, label=name)


def severity(data: Path) -> dict[str, float]:
    """Mean and spread of the PSNR (dB) of a curated folder's pairs, corrupted vs clean (a pair's:
    the mean over its frames). A frame left exactly clean (a haze pair's frames far from its
    Gaussians) counts as one 8-bit unit of error in one value, the least an 8-bit frame can
    differ (95 dB at 128x128), not as +inf, which would make every mean infinite."""
    from morphgs import media
    from morphgs.curation import manifest
    from morphgs.metrics import psnr

    vals = []
    for rec in sorted(manifest.load(data).values(), key=lambda r: r["pair_id"]):
        clean = media.read_clip(data / rec["paths"]["clean"])
        bad = media.read_clip(data / rec["paths"]["corrupted"])
        frames = np.asarray(psnr(bad, clean, reduction="none"), np.float64)
        least = 10 * np.log10(255.0**2 * clean[0].size)  # MSE of one unit in one of the frame's values
        vals.append(float(np.minimum(frames, least).mean()))
    a = np.asarray(vals)
    return {"psnr_mean": float(a.mean()), "psnr_min": float(a.min()), "psnr_max": float(a.max()), "pairs": len(vals)}


def link_fits(folders: list[Path], into: Path) -> None:
    """A relative symlink `into/<scene>` to each per-scene fit folder (kept when it is there)."""
    import os

    into.mkdir(parents=True, exist_ok=True)
    for f in folders:
        link = into / f.name
        if not link.exists() and not link.is_symlink():
            tmp = into / f".{f.name}.tmp{os.getpid()}"
            os.symlink(os.path.relpath(f.resolve(), into.resolve()), tmp)
            os.replace(tmp, link)


def make(work: Path, *, scene_dirs: list[str], spec: Any, pairs_per_scene: int, frames: int,
         size: tuple[int, int], seed: int, calibration_dir: str | None, clean: str, fits: list[str]) -> None:
    """Curate the condition into `work/data` and write `work/severity.json` (`spec` is the label
    of a calibrated condition, whose config is read from `calibration_dir`, else a ConfigSpec;
    `clean`: "render", pairs along the capture path with the clean scene's render as the clean
    side, or "photo", pairs at runs of the capture's photos with the photos as the clean side).
    `fits`: the outputs of the condition's per-scene fit jobs (stages/pairfits.py), linked into
    `work/data/fits` first, so curate finds every fit made and only renders the pairs."""
    from morphgs.ablation.stages.common import curate_condition
    from morphgs.ablation.stages.pairfits import fit_folders

    if calibration_dir is not None:
        spec = calibrated_spec(spec, calibration_dir)

    data = work / "data"
    link_fits(fit_folders(fits), data / "fits")
    curate_condition(scene_dirs, data, spec, pairs_per_scene=pairs_per_scene, frames=frames, size=size, seed=seed,
                     clean=clean, what=f"training set {spec.label}")
    (work / "severity.json").write_text(json.dumps(severity(data), indent=1, sort_keys=True) + "\n",
                                        encoding="utf-8")
