"""Shared pieces of the training tests: tiny curated folders (real `morphgs curate` output from
small built-in scenes) and a model config small enough to train in seconds on a CPU."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import morphgs

# a tiny refiner of ~15k parameters: two levels, H and W multiples of 4
SMALL_MODEL: dict[str, Any] = {"channels": [8, 16], "blocks": [1, 1], "unshuffle": 2, "attention_heads": 2,
                               "groups": 4}


def small_overrides(**sections: dict[str, Any]) -> dict[str, Any]:
    """Overrides for fast test runs: the small model, 4-frame 32x32 clips, fp32, one thread."""
    base: dict[str, Any] = {
        "model": dict(SMALL_MODEL),
        "data": {"frames": 4, "size": [32, 32], "num_workers": 0, "flip": False},
        "optim": {"max_steps": 10, "lr": 2e-3},
        "run": {"mixed_precision": "no", "log_every": 1, "checkpoint_every": 5, "validate_every": 0,
                "threads": 1, "val_clips": 1},
    }
    out = copy.deepcopy(base)
    for name, values in sections.items():
        out.setdefault(name, {}).update(values)
    return out


def curated(out: Path, *, pairs_per_scene: int = 2, frames: int = 8, resolution: tuple[int, int] = (48, 40),
            test_fraction: float = 0.5, gaussians: int = 3000, **kw: Any) -> Path:
    """A curated folder of the two built-in scenes (split seed 0: sample-0 is test, sample-1 train
    at test_fraction 0.5)."""
    morphgs.curate([], out, pairs_per_scene=pairs_per_scene, frames=frames, resolution=resolution,
                   test_fraction=test_fraction, builtin_gaussians=gaussians, progress=False, **kw)
    return out
