"""The model registry (after timm's `_registry.py` / `create_model`): refiners register under a
name, and the training loop, checkpoints and `morphgs refine` look them up by that name and
never branch on it.

Built-in models live in their own modules, imported only when their name is asked for, so
naming `tiny` never imports diffusers. Other packages add models through the `morphgs.models`
entry-point group (`name = "package.module"`; importing the module registers the model).

```python
from morphgs.models import register_model, Refiner

@register_model("mine", config="mine.toml", description="...")
def build(cfg: dict, ctx: ModelContext) -> Refiner: ...
```
"""

from __future__ import annotations

import importlib
import importlib.resources
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from morphgs._core import MorphgsError

if TYPE_CHECKING:
    from morphgs.models.base import ModelContext, Refiner

__all__ = ["ModelEntry", "UnknownModelError", "create_model", "default_config_text", "get_model",
           "list_models", "register_model"]

# name -> module that registers it (imported on first use)
_BUILTIN = {
    "tiny": "morphgs.models.tiny",
    "sandbox": "morphgs.models.sandbox",
    "controlnet": "morphgs.models.controlnet",
}
_REGISTRY: dict[str, ModelEntry] = {}


class UnknownModelError(MorphgsError):
    """A model name nobody registered."""


@dataclass(frozen=True)
class ModelEntry:
    """A registered refiner.

    Attributes:
        name: the registry name (`--model NAME`).
        build: `build(model_config: dict, ctx: ModelContext) -> Refiner`, a fresh model (base
            weights loaded, trainable weights initialised) from its config section.
        config: file name of its default run config under `morphgs/configs/`.
        description: one line for `morphgs train --list-models`.
    """

    name: str
    build: Callable[[dict[str, Any], ModelContext], Refiner]
    config: str
    description: str = ""


def register_model(name: str, *, config: str, description: str = "") -> Callable[[Any], Any]:
    """Decorator registering `build` under `name` (a second registration of a name is refused)."""

    def deco(build: Callable[[dict[str, Any], ModelContext], Refiner]) -> Callable[..., Refiner]:
        if name in _REGISTRY and _REGISTRY[name].build is not build:
            raise ValueError(f"model {name!r} is already registered")
        _REGISTRY[name] = ModelEntry(name, build, config, description)
        return build

    return deco


def _plugin_modules() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group="morphgs.models")}


def list_models() -> list[str]:
    """Every model name that can be asked for (built-in, registered, and plugins)."""
    return sorted(set(_BUILTIN) | set(_REGISTRY) | set(_plugin_modules()))


def get_model(name: str) -> ModelEntry:
    """The registry entry of `name`, importing its module on first use.

    Raises:
        UnknownModelError: no such model (lists the known ones). ImportError: its module exists
        but cannot be imported (e.g. a missing extra).
    """
    if name not in _REGISTRY:
        module = _BUILTIN.get(name) or _plugin_modules().get(name)
        if module is None:
            raise UnknownModelError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as e:
            if e.name == module:
                raise UnknownModelError(f"model {name!r} is not available in this version of morphgs "
                                        f"(no module {module})") from None
            raise
        if name not in _REGISTRY:
            raise UnknownModelError(f"importing {module} did not register a model named {name!r}")
    return _REGISTRY[name]


def create_model(name: str, model_config: dict[str, Any], ctx: ModelContext) -> Refiner:
    """Build a fresh `name` refiner from its config section."""
    return get_model(name).build(dict(model_config), ctx)


def default_config_text(name: str) -> str:
    """The text of a model's default run config (shipped in `morphgs/configs/`)."""
    entry = get_model(name)
    return importlib.resources.files("morphgs.configs").joinpath(entry.config).read_text(encoding="utf-8")
