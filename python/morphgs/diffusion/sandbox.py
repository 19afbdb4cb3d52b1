"""The `sandbox` refiner's network: SD 1.5 UNet + AnimateDiff motion modules, from local folders.

Built as the paper does: `UNetMotionModel.from_unet2d(UNet2DConditionModel, MotionAdapter)`,
conv_in widened from 4 to 8 input channels for [noisy latent, conditioning latent] with
``W[:, :4] = W_base``, ``W[:, 4:] = 0.1 * W_base`` and the bias copied, then LoRA (peft) on the
``to_q, to_k, to_v, to_out.0`` projections of both the spatial and the motion attention. conv_in
and the LoRA weights train; everything else is frozen.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import torch
from torch import nn

from morphgs.diffusion.errors import ModelFolderError
from morphgs.diffusion.folders import DIFFUSERS, TOKENIZER, TRANSFORMERS, require_file, require_folder

__all__ = [
    "LORA_TARGETS",
    "MOTION_ADAPTER_PARTS",
    "SD15_PARTS",
    "SD15Parts",
    "add_lora",
    "build_motion_unet",
    "count_lora_parameters",
    "load_motion_adapter",
    "load_sd15",
    "trainable_state_dict",
    "widen_conv_in",
]

#: subfolders of an SD 1.5 model folder in diffusers layout (the scheduler folder is not read:
#: the DDPM schedule comes from explicit keyword arguments, see `morphgs.diffusion.objectives`)
SD15_PARTS = {"unet": DIFFUSERS, "vae": DIFFUSERS, "text_encoder": TRANSFORMERS, "tokenizer": TOKENIZER}
#: a motion adapter folder is one diffusers model (config.json + weights)
MOTION_ADAPTER_PARTS = {"": DIFFUSERS}
#: the attention projections LoRA wraps; a peft list entry matches a module whose name equals it
#: or ends with ``.entry``, so these hit spatial (``attentions``) and motion
#: (``motion_modules``) attention alike
LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0")
_SINGLE_FILE = (".safetensors", ".ckpt", ".pt", ".bin")


@dataclass
class SD15Parts:
    """The pieces of an SD 1.5 model the sandbox uses."""

    unet: Any  # diffusers.UNet2DConditionModel
    vae: Any  # diffusers.AutoencoderKL
    text_encoder: Any  # transformers.CLIPTextModel
    tokenizer: Any


def _require_config_folder(config_dir: str | os.PathLike[str] | None, *, what: str, checkpoint: Path,
                           needs: Sequence[str]) -> Path:
    if config_dir is None:
        raise ModelFolderError(
            f"{what} {checkpoint} is a single file: also give a local folder of its diffusers configs "
            f"({', '.join(needs)}) as the config folder; the hub is never asked for them")
    root = Path(config_dir).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"config folder for {checkpoint} not found: {root}")
    missing = [n for n in needs if not (root / n).is_file()]
    if missing:
        raise ModelFolderError(f"config folder {root} (for {checkpoint}) is incomplete: missing {', '.join(missing)}")
    return root


def load_sd15(path: str | os.PathLike[str], *, config_dir: str | os.PathLike[str] | None = None,
              variant: str | None = None) -> SD15Parts:
    """Load the UNet, VAE, text encoder and tokenizer of an SD 1.5 model from local files.

    Args:
        path: a diffusers-layout folder (unet/, vae/, text_encoder/, tokenizer/), or a single-file
            checkpoint (.safetensors/.ckpt) in the original layout.
        config_dir: for a single file, a local diffusers-layout folder holding model_index.json,
            the component configs and the tokenizer (no weights needed). Ignored for a folder.
        variant: weight variant of the folder's files (``"fp16"``), or None.

    Returns:
        The parts, in float32 and eval mode.

    Raises:
        FileNotFoundError: the path (or the config folder) does not exist.
        ModelFolderError: the folder is incomplete or the single file lacks its config folder;
            the message names every missing part.
    """
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import AutoTokenizer, CLIPTextModel

    p = Path(path).expanduser()
    if p.is_file():
        ckpt = require_file(p, what="SD 1.5 checkpoint", suffixes=_SINGLE_FILE)
        cfg = _require_config_folder(config_dir, what="SD 1.5 checkpoint", checkpoint=ckpt, needs=(
            "model_index.json", "unet/config.json", "vae/config.json", "text_encoder/config.json"))
        require_folder(cfg, {"tokenizer": TOKENIZER}, what="SD 1.5 config folder")
        from diffusers import StableDiffusionPipeline

        pipe = StableDiffusionPipeline.from_single_file(
            str(ckpt), config=str(cfg), local_files_only=True, safety_checker=None,
            requires_safety_checker=False)
        parts = SD15Parts(pipe.unet, pipe.vae, pipe.text_encoder, pipe.tokenizer)
    else:
        root = require_folder(p, SD15_PARTS, what="SD 1.5 model folder", variant=variant)
        kw: dict[str, Any] = {"local_files_only": True, "variant": variant}
        parts = SD15Parts(
            unet=UNet2DConditionModel.from_pretrained(root, subfolder="unet", **kw),
            vae=AutoencoderKL.from_pretrained(root, subfolder="vae", **kw),
            text_encoder=CLIPTextModel.from_pretrained(root / "text_encoder", **kw),
            tokenizer=AutoTokenizer.from_pretrained(root / "tokenizer", local_files_only=True),
        )
    for m in (parts.unet, parts.vae, parts.text_encoder):
        m.to(torch.float32).eval().requires_grad_(False)
    return parts


def load_motion_adapter(path: str | os.PathLike[str], *, config_dir: str | os.PathLike[str] | None = None,
                        variant: str | None = None) -> Any:
    """Load an AnimateDiff `MotionAdapter` (v1.5.2 in the paper) from local files.

    Args:
        path: a diffusers-layout adapter folder (config.json + weights), or an original single-file
            motion module (``mm_sd_v15_v2.ckpt`` / ``.safetensors``).
        config_dir: for a single file, a local folder holding the adapter's config.json.
        variant: weight variant of the folder's files, or None.

    Raises:
        FileNotFoundError: the path does not exist.
        ModelFolderError: the folder is incomplete or the single file lacks a config folder.
    """
    from diffusers import MotionAdapter

    p = Path(path).expanduser()
    if p.is_file():
        ckpt = require_file(p, what="motion adapter checkpoint", suffixes=_SINGLE_FILE)
        cfg = _require_config_folder(config_dir, what="motion adapter checkpoint", checkpoint=ckpt,
                                     needs=("config.json",))
        adapter = MotionAdapter.from_single_file(str(ckpt), config=str(cfg), local_files_only=True)
    else:
        root = require_folder(p, MOTION_ADAPTER_PARTS, what="motion adapter folder", variant=variant)
        adapter = MotionAdapter.from_pretrained(root, local_files_only=True, variant=variant)
    return adapter.to(torch.float32).eval().requires_grad_(False)


def widen_conv_in(unet: Any, *, in_channels: int = 8, cond_scale: float = 0.1) -> None:
    """Widen a UNet's conv_in for [noisy latent, conditioning latent] inputs, in place.

    The new weight is ``[W_base, cond_scale * W_base, ...]`` along the input channels (the base
    weight repeated per extra group of ``W_base.shape[1]`` channels), the bias is copied, and
    ``in_channels`` is recorded in the model config so `save_pretrained`/`from_pretrained`
    round-trip.

    Args:
        unet: a `UNet2DConditionModel` or `UNetMotionModel`.
        in_channels: the new input channel count, a multiple of the current one.
        cond_scale: factor on the copies that read the conditioning latents (0.1 in the paper).

    Raises:
        ValueError: in_channels is not a multiple of the current count.
    """
    old: Any = unet.conv_in
    c = old.in_channels
    if in_channels == c:
        return
    if in_channels % c:
        raise ValueError(f"conv_in: {in_channels} input channels is not a multiple of the current {c}")
    new = nn.Conv2d(in_channels, old.out_channels, kernel_size=old.kernel_size, stride=old.stride,
                    padding=old.padding, dilation=old.dilation, bias=old.bias is not None,
                    device=old.weight.device, dtype=old.weight.dtype)
    with torch.no_grad():
        w = old.weight
        new.weight.copy_(torch.cat([w] + [cond_scale * w] * (in_channels // c - 1), dim=1))
        if old.bias is not None and new.bias is not None:
            new.bias.copy_(old.bias)
    unet.conv_in = new
    unet.register_to_config(in_channels=in_channels)


def add_lora(unet: Any, *, rank: int = 64, alpha: float = 128, dropout: float = 0.05,
             targets: Sequence[str] = LORA_TARGETS, adapter_name: str = "default") -> None:
    """Add a peft LoRA adapter to a UNet and leave exactly LoRA + conv_in trainable.

    peft marks every non-LoRA parameter frozen when it injects the adapter; conv_in is
    re-enabled afterwards (the widened conv has to learn to read the conditioning latents).

    Args:
        unet: the motion UNet (diffusers `PeftAdapterMixin`).
        rank: LoRA rank r.
        alpha: LoRA alpha (scale alpha / r).
        dropout: dropout on the LoRA input.
        targets: module names (peft list semantics: exact name or ``.name`` suffix).
        adapter_name: the adapter's name.
    """
    from peft import LoraConfig

    unet.requires_grad_(False)
    cfg = LoraConfig(r=rank, lora_alpha=cast(Any, alpha), lora_dropout=dropout, target_modules=list(targets),
                     init_lora_weights=True)
    unet.add_adapter(cfg, adapter_name=adapter_name)
    unet.conv_in.requires_grad_(True)


def count_lora_parameters(unet: Any, *, rank: int, targets: Sequence[str] = LORA_TARGETS) -> int:
    """How many parameters LoRA of a given rank adds on the target linears of a model:
    ``r * (in_features + out_features)`` per wrapped `nn.Linear` (A is r x in, B is out x r)."""
    total = 0
    for name, mod in unet.named_modules():
        base = getattr(mod, "base_layer", mod)
        if isinstance(base, nn.Linear) and any(name == t or name.endswith("." + t) for t in targets):
            total += rank * (base.in_features + base.out_features)
    return total


def build_motion_unet(unet2d: Any, adapter: Any, *, in_channels: int = 8, cond_scale: float = 0.1,
                      lora_rank: int = 64, lora_alpha: float = 128, lora_dropout: float = 0.05,
                      lora_targets: Sequence[str] = LORA_TARGETS) -> Any:
    """The sandbox network: motion UNet, widened conv_in, LoRA; trainable = LoRA + conv_in.

    Args:
        unet2d: SD 1.5 `UNet2DConditionModel` (4 input channels).
        adapter: AnimateDiff `MotionAdapter`.
        in_channels: conv_in input channels after widening.
        cond_scale: factor on the conditioning part of conv_in.
        lora_rank, lora_alpha, lora_dropout, lora_targets: as `add_lora`; rank 0 adds no LoRA.

    Raises:
        ModelFolderError: the adapter does not fit the UNet (block or layer counts differ).
    """
    from diffusers import UNetMotionModel

    try:
        model = UNetMotionModel.from_unet2d(unet2d, adapter)
    except ValueError as e:
        raise ModelFolderError(f"motion adapter does not fit the SD 1.5 UNet: {e}") from None
    widen_conv_in(model, in_channels=in_channels, cond_scale=cond_scale)
    if lora_rank > 0:
        add_lora(model, rank=lora_rank, alpha=lora_alpha, dropout=lora_dropout, targets=lora_targets)
    else:
        model.requires_grad_(False)
        model.conv_in.requires_grad_(True)
    return model


def trainable_state_dict(module: nn.Module) -> dict[str, torch.Tensor]:
    """The parameters that train (LoRA + conv_in for the sandbox), detached, by full name."""
    return {n: p.detach() for n, p in module.named_parameters() if p.requires_grad}
