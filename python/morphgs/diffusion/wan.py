"""Wan2.x base models from a local diffusers-layout folder: one or two transformer experts,
the VAE, the UMT5 text encoder and its tokenizer.

- Wan2.2 T2V-A14B: ``transformer/`` (high-noise expert) and ``transformer_2/`` (low-noise expert),
  switched at ``boundary_ratio`` (0.875 in its model_index.json): the high-noise expert runs
  where ``timestep >= boundary_ratio * 1000``.
- Wan2.2 TI2V-5B: one transformer, the Wan2.2 VAE (48 channels, 16x spatial) and per-token
  timesteps (``expand_timesteps`` in its model_index.json).
- Wan2.1 T2V: one transformer.

``boundary_ratio`` and ``expand_timesteps`` are read from model_index.json when present.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import torch

from morphgs.diffusion.errors import ModelFolderError
from morphgs.diffusion.folders import DIFFUSERS, TOKENIZER, TRANSFORMERS, read_json, require_folder

__all__ = ["WAN_PARTS", "WanParts", "expert_index", "load_wan", "timestep_input"]

WAN_PARTS = {"transformer": DIFFUSERS, "vae": DIFFUSERS, "text_encoder": TRANSFORMERS, "tokenizer": TOKENIZER}


@dataclass
class WanParts:
    """A Wan base model's pieces (all frozen).

    Attributes:
        experts: the transformers, high-noise expert first (one for TI2V-5B / Wan2.1).
        boundary_ratio: expert switch (timestep >= ratio * 1000 runs ``experts[0]``), or None.
        expand_timesteps: pass per-token timesteps (B, L) as the TI2V-5B pipeline does.
    """

    experts: list[Any]
    vae: Any
    text_encoder: Any
    tokenizer: Any
    boundary_ratio: float | None = None
    expand_timesteps: bool = False
    index: dict[str, Any] = field(default_factory=dict)


def load_wan(path: str | os.PathLike[str], *, dtype: torch.dtype = torch.bfloat16, variant: str | None = None,
             boundary_ratio: float | None = None) -> WanParts:
    """Load a Wan base model from a local diffusers-layout folder.

    Args:
        path: the folder (transformer/, optional transformer_2/, vae/, text_encoder/, tokenizer/,
            optional model_index.json).
        dtype: dtype of the transformers and the text encoder (the VAE stays float32; modules the
            models mark keep-in-fp32 stay float32).
        variant: weight variant of the files, or None.
        boundary_ratio: override of model_index.json's expert boundary.

    Returns:
        The parts, frozen and in eval mode.

    Raises:
        FileNotFoundError: no such folder.
        ModelFolderError: a part is missing (all are named), or a two-expert boundary without
            transformer_2/.
    """
    from diffusers import AutoencoderKLWan, WanTransformer3DModel
    from transformers import AutoTokenizer, UMT5EncoderModel

    root = require_folder(path, WAN_PARTS, what="Wan model folder", variant=variant)
    index = read_json(root / "model_index.json", what="Wan model_index.json") \
        if (root / "model_index.json").is_file() else {}
    ratio = boundary_ratio if boundary_ratio is not None else index.get("boundary_ratio")
    two = (root / "transformer_2").is_dir()
    if two:
        require_folder(root, {"transformer_2": DIFFUSERS}, what="Wan model folder", variant=variant)
    if ratio is not None and not two:
        raise ModelFolderError(f"Wan model folder {root}: boundary_ratio {ratio} switches between two experts, "
                               "but transformer_2/ is missing")
    if two and ratio is None:
        raise ModelFolderError(f"Wan model folder {root}: transformer_2/ present but no boundary_ratio "
                               "(in model_index.json or the config)")
    kw: dict[str, Any] = {"local_files_only": True, "variant": variant}
    experts = [WanTransformer3DModel.from_pretrained(root, subfolder=s, torch_dtype=dtype, **kw)
               for s in (["transformer", "transformer_2"] if two else ["transformer"])]
    parts = WanParts(
        experts=experts,
        vae=AutoencoderKLWan.from_pretrained(root, subfolder="vae", torch_dtype=torch.float32, **kw),
        text_encoder=UMT5EncoderModel.from_pretrained(root / "text_encoder", dtype=dtype, **kw),
        tokenizer=AutoTokenizer.from_pretrained(root / "tokenizer", local_files_only=True),
        boundary_ratio=None if ratio is None else float(ratio),
        expand_timesteps=bool(index.get("expand_timesteps", False)),
        index=index,
    )
    for m in [*parts.experts, parts.vae, parts.text_encoder]:
        m.eval().requires_grad_(False)
    return parts


def expert_index(timesteps: torch.Tensor, boundary_ratio: float | None, *, num_train_timesteps: int = 1000) -> torch.Tensor:
    """Which expert runs each timestep: 0 (high noise) where ``t >= ratio * 1000`` or with one
    expert, 1 (low noise) otherwise; int64 like ``timesteps``."""
    if boundary_ratio is None:
        return torch.zeros_like(timesteps, dtype=torch.int64)
    return (timesteps < boundary_ratio * num_train_timesteps).to(torch.int64)


def timestep_input(timesteps: torch.Tensor, latent_shape: torch.Size | tuple[int, ...], patch_size: tuple[int, ...],
                   *, expand: bool) -> torch.Tensor:
    """The transformer's timestep argument: (B,) or, for TI2V-style models, (B, L) with the
    timestep repeated on every token (what `WanPipeline` passes with ``expand_timesteps``)."""
    if not expand:
        return timesteps
    _, _, f, h, w = latent_shape
    tokens = (f // patch_size[0]) * (h // patch_size[1]) * (w // patch_size[2])
    return timesteps.view(-1, 1).expand(-1, tokens)

