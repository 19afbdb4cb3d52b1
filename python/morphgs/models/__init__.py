"""Refiners: the registry (`create_model`, `register_model`, `list_models`) and the `Refiner`
protocol the training loop, checkpoints and `morphgs refine` rely on (morphgs.models.base).
Importing this package imports torch; a model's own module (and its dependencies, e.g.
diffusers) is imported only when its name is asked for.
"""

from __future__ import annotations

from morphgs.models.base import CheckpointError, ModelContext, Refiner
from morphgs.models.registry import (ModelEntry, UnknownModelError, create_model, default_config_text, get_model,
                                     list_models, register_model)

__all__ = [
    "CheckpointError",
    "ModelContext",
    "ModelEntry",
    "Refiner",
    "UnknownModelError",
    "create_model",
    "default_config_text",
    "get_model",
    "list_models",
    "register_model",
]
