"""`sandbox`: the paper's diagnostic refiner, SD 1.5 UNet + AnimateDiff motion modules with conv_in
widened to 8 channels and LoRA on spatial and motion attention, trained with DDPM epsilon
prediction on cached VAE latents (`morphgs.diffusion.sandbox_refiner`; docs/refiners.md).
Needs `pip install 'morphgs[diffusion]'` and local SD 1.5 and motion adapter folders."""

from __future__ import annotations

from typing import Any

from morphgs.configfile import config_from_dict
from morphgs.diffusion.sandbox_refiner import SandboxRefiner, SandboxSettings
from morphgs.models.base import ModelContext
from morphgs.models.registry import register_model

__all__ = ["build"]


@register_model("sandbox", config="sandbox.toml",
                description="SD 1.5 + AnimateDiff, conv_in 4->8, LoRA r64 (DDPM; local model folders)")
def build(cfg: dict[str, Any], ctx: ModelContext) -> SandboxRefiner:
    """A sandbox refiner from its [model] table (base weights from the local folders it names)."""
    return SandboxRefiner(config_from_dict(SandboxSettings, cfg, section="model"), ctx)
