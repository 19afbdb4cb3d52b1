"""`controlnet`: the paper's scaled refiner, a frozen Wan2.2 DiT (A14B's two experts, or TI2V-5B)
driven by a trainable dilated ControlNet (8 blocks copied from base blocks 0, 3, ..., 21), trained
with flow matching on cached VAE latents (`morphgs.diffusion.controlnet_refiner`;
docs/refiners.md). Needs `pip install 'morphgs[diffusion]'` and a local Wan folder."""

from __future__ import annotations

from typing import Any

from morphgs._core import MorphgsError
from morphgs.configfile import config_from_dict

try:
    import diffusers  # noqa: F401
    import transformers  # noqa: F401
except ImportError as e:  # a clear message instead of a traceback from deep inside
    raise MorphgsError(f"model 'controlnet' needs the diffusion extra: pip install 'morphgs[diffusion]' ({e})") \
        from None

from morphgs.diffusion.controlnet_refiner import ControlNetRefiner, ControlNetSettings  # noqa: E402
from morphgs.models.base import ModelContext  # noqa: E402
from morphgs.models.registry import register_model  # noqa: E402

__all__ = ["build"]


@register_model("controlnet", config="controlnet.toml",
                description="Wan2.2 DiT + dilated ControlNet (8 blocks, stride 3), flow matching; local Wan folder")
def build(cfg: dict[str, Any], ctx: ModelContext) -> ControlNetRefiner:
    """A controlnet refiner from its [model] table (base weights from the local Wan folder)."""
    return ControlNetRefiner(config_from_dict(ControlNetSettings, cfg, section="model"), ctx)
