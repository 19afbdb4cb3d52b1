"""Write a diffusers SD 1.5 model (UNet, VAE, CLIP text encoder) as one original-layout (LDM)
single-file checkpoint, for testing the single-file loading path without downloading one.

The inverse of diffusers' `convert_ldm_unet_checkpoint`, `convert_ldm_vae_checkpoint` and
`convert_ldm_clip_checkpoint` (diffusers/loaders/single_file_utils.py), after the key tables of
diffusers' scripts/convert_diffusers_to_original_stable_diffusion.py, generalised to any block
and layer count.
"""

from __future__ import annotations

from typing import Any

import torch

_RESNET = [("norm1", "in_layers.0"), ("conv1", "in_layers.2"), ("norm2", "out_layers.0"), ("conv2", "out_layers.3"),
           ("time_emb_proj", "emb_layers.1"), ("conv_shortcut", "skip_connection")]
_UNET_TOP = {"time_embedding.linear_1": "time_embed.0", "time_embedding.linear_2": "time_embed.2",
             "conv_in": "input_blocks.0.0", "conv_norm_out": "out.0", "conv_out": "out.2"}
_VAE_ATTN = [("group_norm.", "norm."), ("to_q.", "q."), ("to_k.", "k."), ("to_v.", "v."), ("to_out.0.", "proj_out.")]


def _prefix_map(unet: Any) -> list[tuple[str, str]]:
    """(diffusers prefix, LDM prefix) pairs of a UNet2DConditionModel."""
    cfg = unet.config
    per = cfg.layers_per_block
    out: list[tuple[str, str]] = [(k + ".", v + ".") for k, v in _UNET_TOP.items()]
    n = len(cfg.down_block_types)
    for i in range(n):
        for j in range(per):
            out.append((f"down_blocks.{i}.resnets.{j}.", f"input_blocks.{(per + 1) * i + j + 1}.0."))
            if hasattr(unet.down_blocks[i], "attentions"):
                out.append((f"down_blocks.{i}.attentions.{j}.", f"input_blocks.{(per + 1) * i + j + 1}.1."))
        if unet.down_blocks[i].downsamplers:
            out.append((f"down_blocks.{i}.downsamplers.0.conv.", f"input_blocks.{(per + 1) * (i + 1)}.0.op."))
        up = unet.up_blocks[i]
        for j in range(per + 1):
            out.append((f"up_blocks.{i}.resnets.{j}.", f"output_blocks.{(per + 1) * i + j}.0."))
            if hasattr(up, "attentions"):
                out.append((f"up_blocks.{i}.attentions.{j}.", f"output_blocks.{(per + 1) * i + j}.1."))
        if up.upsamplers:
            slot = 2 if hasattr(up, "attentions") else 1
            out.append((f"up_blocks.{i}.upsamplers.0.", f"output_blocks.{(per + 1) * i + per}.{slot}."))
    out += [("mid_block.attentions.0.", "middle_block.1."), ("mid_block.resnets.0.", "middle_block.0."),
            ("mid_block.resnets.1.", "middle_block.2.")]
    return out


def unet_to_ldm(unet: Any) -> dict[str, torch.Tensor]:
    prefixes = sorted(_prefix_map(unet), key=lambda p: -len(p[0]))
    out = {}
    for k, v in unet.state_dict().items():
        hf, ldm = next((a, b) for a, b in prefixes if k.startswith(a))
        rest = k[len(hf):]
        if ".resnets." in hf or hf.startswith("mid_block.resnets"):
            for a, b in _RESNET:
                rest = rest.replace(a, b)
        out["model.diffusion_model." + ldm + rest] = v
    return out


def vae_to_ldm(vae: Any) -> dict[str, torch.Tensor]:
    n = len(vae.config.down_block_types)
    pairs = [("encoder.conv_norm_out.", "encoder.norm_out."), ("decoder.conv_norm_out.", "decoder.norm_out."),
             ("encoder.mid_block.attentions.0.", "encoder.mid.attn_1."),
             ("decoder.mid_block.attentions.0.", "decoder.mid.attn_1.")]
    for side in ("encoder", "decoder"):
        pairs += [(f"{side}.mid_block.resnets.{i}.", f"{side}.mid.block_{i + 1}.") for i in range(2)]
    for i in range(n):
        pairs += [(f"encoder.down_blocks.{i}.resnets.", f"encoder.down.{i}.block."),
                  (f"encoder.down_blocks.{i}.downsamplers.0.", f"encoder.down.{i}.downsample."),
                  (f"decoder.up_blocks.{i}.resnets.", f"decoder.up.{n - 1 - i}.block."),
                  (f"decoder.up_blocks.{i}.upsamplers.0.", f"decoder.up.{n - 1 - i}.upsample.")]
    pairs.sort(key=lambda p: -len(p[0]))
    out = {}
    for k, v in vae.state_dict().items():
        key = k
        for a, b in pairs:
            if key.startswith(a):
                key = b + key[len(a):]
                break
        key = key.replace("conv_shortcut", "nin_shortcut")
        if ".attn_1." in key:
            for a, b in _VAE_ATTN:
                key = key.replace(a, b)
            if v.ndim == 2:  # linear -> the original 1x1 conv
                v = v[:, :, None, None]
        out["first_stage_model." + key] = v
    return out


def clip_to_ldm(text_encoder: Any) -> dict[str, torch.Tensor]:
    # the original checkpoints hold a transformers CLIPTextModel under "cond_stage_model.transformer."
    # with its "text_model." prefix (transformers 5 dropped that prefix from the state dict)
    out = {}
    for k, v in text_encoder.state_dict().items():
        out["cond_stage_model.transformer." + (k if k.startswith("text_model.") else "text_model." + k)] = v
    return out


def sd15_to_ldm(unet: Any, vae: Any, text_encoder: Any) -> dict[str, torch.Tensor]:
    """One LDM-layout state dict of the three models (contiguous tensors, ready for save_file)."""
    out = {**unet_to_ldm(unet), **vae_to_ldm(vae), **clip_to_ldm(text_encoder)}
    return {k: v.detach().contiguous().clone() for k, v in out.items()}
