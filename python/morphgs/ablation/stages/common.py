"""What several stages share: torch's thread count for a job, reading a test set's index, and the
FitConfig of the sparse fits, re-fits and clean fits."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["fit_config", "read_testset", "torch_threads"]


def torch_threads(threads: int) -> None:
    """Fix torch's intra-op threads for this job (0 leaves torch's default). The bytes do not
    depend on it: the stages that take `threads` list it in their IGNORE."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))


def read_testset(testset_dir: str | Path) -> dict[str, Any]:
    """testset.json of a finished test-set output: scene, regime, train_views, capture_views,
    clips (their folder names under clips/) and bbox_diagonal."""
    return dict(json.loads((Path(testset_dir) / "testset.json").read_text(encoding="utf-8")))


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


def curate_condition(scene_dirs: list[str], data: Path, spec: Any, *, pairs_per_scene: int, frames: int,
                     size: tuple[int, int], seed: int, clean: str, what: str) -> None:
    """Curate one condition's pairs of `scene_dirs` into `data`, as a training set makes them
    (no test split; `clean`: "render", pairs along the capture path with the clean scene's render
    as the clean side, or "photo", pairs at runs of the capture's photos); a failed pair raises
    StudyError naming `what`."""
    from morphgs.ablation.study import StudyError
    from morphgs.curation import curate

    summary = curate(scene_dirs, data, configs=[spec], pairs_per_scene=pairs_per_scene, frames=frames,
                     resolution=size, seed=seed, test_fraction=0.0,
                     trajectory="photos" if clean == "photo" else "cameras", progress=False,
                     log=lambda m: None)
    if not summary.ok:
        raise StudyError(f"{what}: curate failed: {summary.failed}")
