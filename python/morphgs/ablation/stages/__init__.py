"""The stages of `morphgs ablate`, one small module each, in the order the recipe runs them
(morphgs.ablation.recipe): cleanfits (captures given as photos), captures, pairfits (the fits of
fit-based training sets, one per scene), trainsets, calibration, training, testsets, refine,
metrics2d, metrics3d, report.

Each stage module has
- `make(work, **arguments)`, which fills a work folder from its arguments alone;
- `VERSION`: bumped whenever what `make()` writes changes (it is in the stage's cache key, so the
  stage and everything downstream of it is made again);
- `IGNORE`: the arguments that do not change the output (thread counts), left out of the key;
- `RESUMABLE`: whether a killed job continues in its work folder (fits, training) or starts over.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["STAGES", "stage_module"]

STAGES = ("cleanfits", "captures", "pairfits", "trainsets", "calibration", "training", "testsets", "refine", "metrics2d", "metrics3d",
          "report")


def stage_module(stage: str) -> ModuleType:
    """The module of a stage (`morphgs.ablation.stages.<stage>`)."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r} (the stages: {', '.join(STAGES)})")
    return importlib.import_module(f"morphgs.ablation.stages.{stage}")
