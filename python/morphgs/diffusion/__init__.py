"""The paper's two diffusion refiners and the parts they share (torch, diffusers, peft).

- `sandbox`: SD 1.5 UNet + AnimateDiff motion modules (`UNetMotionModel`), conv_in widened to
  8 channels, LoRA on spatial and motion attention, DDPM epsilon objective.
- `controlnet`: a frozen Wan2.2 DiT (`WanTransformer3DModel`, one or two experts) driven by a
  trainable dilated ControlNet (blocks copied from the base at a stride), flow-matching objective.

Every submodule imports torch/diffusers itself; importing this package imports nothing heavy.
Install with ``pip install 'morphgs[diffusion]'``.
"""

from __future__ import annotations

from morphgs.diffusion.errors import LatentCacheError, ModelFolderError

__all__ = ["LatentCacheError", "ModelFolderError"]
