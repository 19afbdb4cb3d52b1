"""Typed errors of the diffusion refiners (no torch import here)."""

from __future__ import annotations

from morphgs._core import MorphgsError

__all__ = ["LatentCacheError", "ModelFolderError"]


class ModelFolderError(MorphgsError):
    """A local model folder (or single-file checkpoint) is incomplete or of the wrong kind.

    The message names the folder and every missing part, for example
    ``/models/sd15: missing unet/config.json, vae weights (vae/diffusion_pytorch_model.safetensors)``.
    """


class LatentCacheError(MorphgsError):
    """A latent cache does not match what the run asks for (another VAE, size, frame count,
    dataset or prompt), or is damaged. The message names the cache folder and each mismatch."""
