"""The dilated ControlNet for a frozen Wan DiT, and the forward pass that injects its residuals.

Design (the paper's "8 blocks copied from the base at stride 3", after TheDenk's dilated
ControlNet for Wan): the ControlNet holds ``num_blocks`` `WanTransformerBlock`s copied from base
blocks ``0, stride, 2*stride, ...`` (blocks 0, 3, ..., 21 for 8 at stride 3; TheDenk's
``--init_from_transformer`` copies blocks 0..7 instead), a zero-initialised patch embedding of the
control latents (the corrupted clip's VAE latents) added to the base's token embedding, and one
zero-initialised output projection per block. After base block ``i * stride`` the i-th residual
is added to the base's hidden states, so at initialisation the combined output equals the base
output exactly.

The ControlNet reuses the running base model's token, timestep, text and rotary embeddings (as
diffusers' `WanVACETransformer3DModel` does for its hint blocks), so one ControlNet serves
whichever Wan2.2 A14B expert runs at a given noise level, and the text projection is not
duplicated.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import torch
from diffusers.configuration_utils import ConfigMixin, register_to_config
from diffusers.models.modeling_utils import ModelMixin
from diffusers.models.transformers.transformer_wan import WanTransformerBlock
from torch import nn
from torch.utils.checkpoint import checkpoint

__all__ = ["DilatedControlNet", "controlled_forward", "injection_layers"]


def injection_layers(num_blocks: int, stride: int) -> list[int]:
    """The base blocks the ControlNet copies and after which it adds its residuals."""
    return [i * stride for i in range(num_blocks)]


class DilatedControlNet(ModelMixin, ConfigMixin):  # type: ignore[misc]
    """A trainable copy of every ``stride``-th block of a Wan transformer, driven by control latents.

    Args:
        num_blocks: ControlNet blocks (8 in the paper).
        stride: base blocks between injections (3 in the paper).
        num_attention_heads, attention_head_dim, ffn_dim, qk_norm, cross_attn_norm, eps,
        added_kv_proj_dim: the base transformer's block settings.
        patch_size: the base transformer's (t, h, w) patch size.
        control_channels: channels of the control latents (the VAE's z_dim).
        base_num_layers: block count of the base it was made for (checked at run time).
    """

    _supports_gradient_checkpointing = True
    _no_split_modules = ["WanTransformerBlock"]  # type: ignore[assignment]
    _keep_in_fp32_modules = ["scale_shift_table", "norm1", "norm2", "norm3"]  # type: ignore[assignment]

    @register_to_config
    def __init__(
        self,
        num_blocks: int = 8,
        stride: int = 3,
        num_attention_heads: int = 40,
        attention_head_dim: int = 128,
        ffn_dim: int = 13824,
        patch_size: Sequence[int] = (1, 2, 2),
        control_channels: int = 16,
        qk_norm: str | None = "rms_norm_across_heads",
        cross_attn_norm: bool = True,
        eps: float = 1e-6,
        added_kv_proj_dim: int | None = None,
        base_num_layers: int = 40,
    ) -> None:
        super().__init__()
        if num_blocks < 1 or stride < 1:
            raise ValueError(f"DilatedControlNet: num_blocks ({num_blocks}) and stride ({stride}) must be >= 1")
        if (num_blocks - 1) * stride >= base_num_layers:
            raise ValueError(
                f"DilatedControlNet: {num_blocks} blocks at stride {stride} reach base block "
                f"{(num_blocks - 1) * stride}, but the base has {base_num_layers} blocks")
        inner = num_attention_heads * attention_head_dim
        p_t, p_h, p_w = (int(v) for v in patch_size)
        self.control_embedding = nn.Conv3d(control_channels, inner, kernel_size=(p_t, p_h, p_w), stride=(p_t, p_h, p_w))
        self.blocks = nn.ModuleList([
            WanTransformerBlock(inner, ffn_dim, num_attention_heads, qk_norm, cross_attn_norm, eps,  # type: ignore[arg-type]
                                added_kv_proj_dim)
            for _ in range(num_blocks)
        ])
        self.proj_out = nn.ModuleList([nn.Linear(inner, inner) for _ in range(num_blocks)])
        self.zero_outputs()
        self.gradient_checkpointing = False

    def zero_outputs(self) -> None:
        """Zero the control embedding and every output projection (the ControlNet's init)."""
        with torch.no_grad():
            for m in [self.control_embedding, *self.proj_out]:
                m.weight.zero_()
                m.bias.zero_()

    @property
    def layers(self) -> list[int]:
        """Base blocks after which residuals are added (0, stride, 2*stride, ...)."""
        cfg: Any = self.config
        return injection_layers(cfg.num_blocks, cfg.stride)

    @classmethod
    def from_transformer(cls, base: Any, *, num_blocks: int = 8, stride: int = 3) -> DilatedControlNet:
        """Make a ControlNet whose blocks are copies of base blocks ``0, stride, ...``.

        Args:
            base: a `WanTransformer3DModel` (an expert of Wan2.2 A14B, TI2V-5B, Wan2.1).
            num_blocks: ControlNet blocks.
            stride: base blocks between copies.

        Returns:
            The ControlNet in float32 (the trainable master weights; copies of bf16 blocks are
            exact), on the base's device, with zero control embedding and output projections.

        Raises:
            ValueError: the blocks would reach past the base's last block.
        """
        c = base.config
        net = cls(num_blocks=num_blocks, stride=stride, num_attention_heads=c.num_attention_heads,
                  attention_head_dim=c.attention_head_dim, ffn_dim=c.ffn_dim, patch_size=tuple(c.patch_size),
                  control_channels=c.in_channels, qk_norm=c.qk_norm, cross_attn_norm=c.cross_attn_norm,
                  eps=c.eps, added_kv_proj_dim=c.added_kv_proj_dim, base_num_layers=c.num_layers)
        net.to(device=base.device)
        with torch.no_grad():
            for i, j in enumerate(net.layers):
                net.blocks[i].load_state_dict(base.blocks[j].state_dict())
        return net

    def check_base(self, base: Any) -> None:
        """Raise ValueError if ``base`` is not a transformer this ControlNet fits."""
        c, mine = base.config, cast(Any, self.config)
        inner = c.num_attention_heads * c.attention_head_dim
        want = mine.num_attention_heads * mine.attention_head_dim
        if inner != want or tuple(c.patch_size) != tuple(mine.patch_size) or c.num_layers <= self.layers[-1]:
            raise ValueError(
                f"DilatedControlNet (width {want}, patch {tuple(mine.patch_size)}, last injection after "
                f"block {self.layers[-1]}) does not fit a base of width {inner}, patch "
                f"{tuple(c.patch_size)} and {c.num_layers} blocks")

    def forward(self, hidden_states: torch.Tensor, control: torch.Tensor, encoder_hidden_states: torch.Tensor,
                timestep_proj: torch.Tensor, rotary_emb: Any) -> tuple[torch.Tensor, ...]:
        """The residuals, one per block.

        Args:
            hidden_states: the base's patch-embedded tokens (B, L, D) of the noisy latents.
            control: control latents (B, C, F, H, W), the same latent size as the noisy latents.
            encoder_hidden_states: the base's projected text embeddings (B, T, D).
            timestep_proj: the base's timestep projection ((B, 6, D) or (B, L, 6, D)).
            rotary_emb: the base's rotary embedding for these tokens.

        Returns:
            ``num_blocks`` tensors (B, L, D).
        """
        c = self.control_embedding(control.to(self.control_embedding.weight.dtype))
        h = hidden_states + c.flatten(2).transpose(1, 2).to(hidden_states.dtype)
        out = []
        for block, proj in zip(self.blocks, self.proj_out):
            if torch.is_grad_enabled() and self.gradient_checkpointing:
                h = checkpoint(block, h, encoder_hidden_states, timestep_proj, rotary_emb, use_reentrant=False)
            else:
                h = block(h, encoder_hidden_states, timestep_proj, rotary_emb)
            out.append(proj(h))
        return tuple(out)


def _embed(base: Any, latents: torch.Tensor, timestep: torch.Tensor,
           encoder_hidden_states: torch.Tensor) -> tuple[Any, ...]:
    """The first half of `WanTransformer3DModel.forward`: tokens, rotary, timestep and text embeddings."""
    rotary_emb = base.rope(latents)
    hidden = base.patch_embedding(latents).flatten(2).transpose(1, 2).contiguous()
    if timestep.ndim == 2:
        ts_seq_len = timestep.shape[1]
        timestep = timestep.flatten()
    else:
        ts_seq_len = None
    temb, timestep_proj, text, _ = base.condition_embedder(timestep, encoder_hidden_states, None,
                                                           timestep_seq_len=ts_seq_len)
    timestep_proj = timestep_proj.unflatten(2, (6, -1)) if ts_seq_len is not None else timestep_proj.unflatten(1, (6, -1))
    return hidden, rotary_emb, temb, timestep_proj, text


def _unpatchify(base: Any, hidden: torch.Tensor, temb: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """The last part of `WanTransformer3DModel.forward`: output norm, projection, unpatchify."""
    b, _, f, h, w = shape
    p_t, p_h, p_w = base.config.patch_size
    if temb.ndim == 3:
        shift, scale = (base.scale_shift_table.unsqueeze(0).to(temb.device) + temb.unsqueeze(2)).chunk(2, dim=2)
        shift, scale = shift.squeeze(2), scale.squeeze(2)
    else:
        shift, scale = (base.scale_shift_table.to(temb.device) + temb.unsqueeze(1)).chunk(2, dim=1)
    shift, scale = shift.to(hidden.device), scale.to(hidden.device)
    hidden = (base.norm_out(hidden.float()) * (1 + scale) + shift).type_as(hidden)
    hidden = base.proj_out(hidden)
    hidden = hidden.reshape(b, f // p_t, h // p_h, w // p_w, p_t, p_h, p_w, -1)
    hidden = hidden.permute(0, 7, 1, 4, 2, 5, 3, 6)
    return hidden.flatten(6, 7).flatten(4, 5).flatten(2, 3)


def controlled_forward(base: Any, controlnet: DilatedControlNet | None, latents: torch.Tensor,
                       timestep: torch.Tensor, encoder_hidden_states: torch.Tensor,
                       control: torch.Tensor | None = None, *, scale: float = 1.0,
                       gradient_checkpointing: bool = False) -> torch.Tensor:
    """A Wan transformer's forward pass with the ControlNet's residuals added after its blocks.

    The same computation as `WanTransformer3DModel.forward` (text-to-video, no image tokens) with
    ``hidden += scale * residual[i]`` after base block ``controlnet.layers[i]``; with no ControlNet
    it is the base's forward pass.

    Args:
        base: the (frozen) `WanTransformer3DModel` that runs at this noise level.
        controlnet: the ControlNet, or None.
        latents: noisy latents (B, C, F, H, W).
        timestep: (B,) or, for TI2V-style per-token timesteps, (B, L).
        encoder_hidden_states: text embeddings (B, T, text_dim).
        control: control latents (B, C', F, H, W); required with a ControlNet.
        scale: factor on the residuals.
        gradient_checkpointing: recompute each block in the backward pass (base and ControlNet).

    Returns:
        The model output (B, C_out, F, H, W): the flow (velocity) prediction.
    """
    hidden, rotary_emb, temb, timestep_proj, text = _embed(base, latents, timestep, encoder_hidden_states)
    residuals: tuple[torch.Tensor, ...] = ()
    at: dict[int, int] = {}
    if controlnet is not None:
        if control is None:
            raise ValueError("controlled_forward: a ControlNet needs control latents")
        controlnet.gradient_checkpointing = gradient_checkpointing
        residuals = controlnet(hidden, control, text, timestep_proj, rotary_emb)
        at = {layer: i for i, layer in enumerate(controlnet.layers)}
    for j, block in enumerate(base.blocks):
        if torch.is_grad_enabled() and gradient_checkpointing:
            hidden = checkpoint(block, hidden, text, timestep_proj, rotary_emb, use_reentrant=False)
        else:
            hidden = block(hidden, text, timestep_proj, rotary_emb)
        if j in at:
            hidden = hidden + residuals[at[j]].to(hidden.dtype) * scale
    return _unpatchify(base, hidden, temb, latents.shape)
