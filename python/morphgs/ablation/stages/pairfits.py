"""Stage 1b, the real fits of fit-based training sets, one job per (condition, training scene): a
target condition's sparse fit of the scene (every K-th view, the study's [sparse] settings), or an
`underfit:F` / `cross:P` condition's fit.

They were the long pole of a study: a training set's one `curate` call fitted its scenes one after
another (at the paper's scale one job fitting 200 scenes, most of the cluster plan's wall time).
Each fit is now its own job, so they spread over the worker pool or the Ray cluster like every
other stage; the training set (stages/trainsets.py) links their fit folders into its own curate
output, where curate finds them done and only renders the pairs. The fit is the one that curate
would have made (same config, size, seed and scene, so the same cache folder and the same bytes).

Each job runs curate on its one scene (pairs included: they are a few renders, and they check
that the fit is usable before the training set is made).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "fit_folders", "make"]

VERSION = 1
IGNORE: tuple[str, ...] = ()
RESUMABLE = True  # curate resumes a killed fit from its checkpoint in this folder


def make(work: Path, *, scene_dir: str, spec: Any, pairs_per_scene: int, frames: int, size: tuple[int, int],
         seed: int, clean: str) -> None:
    """Curate `spec` on the one scene `scene_dir` into `work/data` (its fit under data/fits/<scene>)."""
    from morphgs.ablation.stages.common import curate_condition

    curate_condition([scene_dir], work / "data", spec, pairs_per_scene=pairs_per_scene, frames=frames, size=size,
                     seed=seed, clean=clean, what=f"fit of {Path(scene_dir).name} for {spec.label}")


def fit_folders(outputs: list[str]) -> list[Path]:
    """The per-scene fit folders (data/fits/<scene>) of pairfits outputs, in order."""
    found = []
    for out in outputs:
        fits = Path(out) / "data" / "fits"
        found += sorted(p for p in fits.iterdir() if p.is_dir()) if fits.is_dir() else []
    return found
