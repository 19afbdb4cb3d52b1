"""Refiner training (torch, accelerate): `train(...)` is `morphgs train`. See docs/training.md.

Needs `pip install 'morphgs[train]'`.
"""

from __future__ import annotations

from morphgs.training.checkpoint import latest_checkpoint, list_checkpoints
from morphgs.training.config import DataConfig, OptimConfig, RunConfig, TrainConfig, resolve_config
from morphgs.training.loop import TrainingError, TrainResult, train

__all__ = [
    "DataConfig",
    "OptimConfig",
    "RunConfig",
    "TrainConfig",
    "TrainResult",
    "TrainingError",
    "latest_checkpoint",
    "list_checkpoints",
    "resolve_config",
    "train",
]
