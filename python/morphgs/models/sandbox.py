"""`sandbox`: the paper's diagnostic refiner, SD 1.5 UNet + AnimateDiff motion modules with conv_in
widened to 8 channels and LoRA on spatial and motion attention, trained with DDPM epsilon
prediction on cached VAE latents (`morphgs.diffusion.sandbox_refiner`; docs/refiners.md).
Needs `pip install 'morphgs[diffusion]'` and local SD 1.5 and motion adapter folders."""

from __future__ import annotations

from typing import Any

from morphgs._core import MorphgsError
from morphgs.configfile import config_from_dict

try:
    import diffusers  # noqa: F401
    import peft  # noqa: F401
    import transformers  # noqa: F401
except ImportError as e:  # a clear message instead of a traceback from deep inside
    raise MorphgsError(f"model 'sandbox' needs the diffusion extra: pip install 'morphgs[diffusion]' ({e})") from None

from morphgs.diffusion.sandbox_refiner import SandboxRefiner, SandboxSettings  # noqa: E402
from morphgs.models.base import ModelContext  # noqa: E402
from morphgs.models.registry import register_model  # noqa: E402

__all__ = ["build"]


@register_model("sandbox", config="sandbox.toml",
                description="SD 1.5 + AnimateDiff, conv_in 4->8, LoRA r64 (DDPM; local model folders)")
def build(cfg: dict[str, Any], ctx: ModelContext) -> SandboxRefiner:
    """A sandbox refiner from its [model] table (base weights from the local folders it names)."""
    return SandboxRefiner(config_from_dict(SandboxSettings, cfg, section="model"), ctx)
