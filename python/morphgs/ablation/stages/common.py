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
