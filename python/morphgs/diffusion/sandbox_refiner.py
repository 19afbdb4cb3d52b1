"""The `sandbox` refiner: SD 1.5 UNet + AnimateDiff motion modules, conv_in 4 -> 8, LoRA, DDPM.

Training input: cached VAE posteriors of clean (target) and corrupted (condition) 16-frame clips
and a cached prompt embedding. Each step draws a fresh target latent from the clean posterior,
noises it at a uniform DDPM timestep, feeds ``[noisy, corrupted latent]`` (8 channels) to the
motion UNet and regresses the noise (epsilon) with MSE. Inference starts from Gaussian noise and
runs N DDIM steps over the same betas (or DDPM), conditioned on the corrupted clip's latents,
then decodes with the VAE (colour correction is the caller's, see `morphgs refine`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from morphgs._core import MorphgsError
from morphgs.diffusion import objectives
from morphgs.diffusion.codecs import LatentNorm, SDCodec, files_fingerprint
from morphgs.diffusion.refiner import DTYPES, LatentRefiner
from morphgs.diffusion.sandbox import LORA_TARGETS, build_motion_unet, load_motion_adapter, load_sd15
from morphgs.diffusion.text import DEFAULT_PROMPT
from morphgs.models.base import ModelContext

__all__ = ["SandboxRefiner", "SandboxSettings"]


@dataclass(frozen=True)
class SandboxSettings:
    """The `[model]` table of a sandbox config (configs/sandbox.toml documents every key); the
    defaults are the paper's. Frames and clip size come from the run's [data] table.

    Attributes:
        sd15: SD 1.5 model folder (diffusers layout) or single-file checkpoint.
        sd15_config: for a single file, a local folder of its diffusers configs and tokenizer.
        motion_adapter: AnimateDiff motion adapter folder (v1.5.2 in the paper) or single file.
        motion_adapter_config: for a single-file adapter, a folder with its config.json.
        variant: weight variant of the folders' files ("fp16"), or None.
        lora_rank, lora_alpha, lora_dropout, lora_targets: LoRA (r 64, alpha 128, dropout 0.05 on
            to_q/to_k/to_v/to_out.0 of spatial and motion attention).
        conv_in_channels, conv_in_cond_scale: conv_in widening (8, 0.1).
        conv_in_lr: conv_in's learning rate (None: the run's).
        prompt, captions: one prompt, or a JSON/JSONL file of per-pair captions.
        weight_dtype: dtype of the frozen weights ("bfloat16" as the paper trains, or "float32").
        gradient_checkpointing: recompute UNet blocks in the backward pass.
        cache_dir, cache_dtype, cache_stride, rebuild_cache: the latent cache (folder; storage
            dtype; window stride, 0 = frames; re-encode a stale one instead of refusing it).
        condition: conditioning latents: the corrupted posterior's "mean" or a fresh "sample".
        inference_steps, sampler: refine's denoising steps and scheduler ("ddim" or "ddpm").
    """

    sd15: str = ""
    sd15_config: str | None = None
    motion_adapter: str = ""
    motion_adapter_config: str | None = None
    variant: str | None = None
    lora_rank: int = 64
    lora_alpha: float = 128.0
    lora_dropout: float = 0.05
    lora_targets: tuple[str, ...] = LORA_TARGETS
    conv_in_channels: int = 8
    conv_in_cond_scale: float = 0.1
    conv_in_lr: float | None = None
    prompt: str = DEFAULT_PROMPT
    captions: str | None = None
    weight_dtype: str = "bfloat16"
    gradient_checkpointing: bool = True
    cache_dir: str | None = None
    cache_dtype: str = "float32"
    cache_stride: int = 0
    rebuild_cache: bool = False
    condition: str = "mean"
    inference_steps: int = 25
    sampler: str = "ddim"

    def __post_init__(self) -> None:
        if not self.sd15:
            raise ValueError("sd15 (the local SD 1.5 model folder or checkpoint) is not set")
        if not self.motion_adapter:
            raise ValueError("motion_adapter (the local AnimateDiff motion adapter folder) is not set")
        if self.weight_dtype not in DTYPES:
            raise ValueError(f"weight_dtype {self.weight_dtype!r} is not one of {', '.join(DTYPES)}")
        if self.condition not in ("mean", "sample"):
            raise ValueError(f"condition {self.condition!r} is not 'mean' or 'sample'")
        if self.sampler not in ("ddim", "ddpm"):
            raise ValueError(f"sampler {self.sampler!r} is not 'ddim' or 'ddpm'")
        if self.lora_rank < 0 or self.inference_steps < 1 or self.cache_stride < 0:
            raise ValueError("lora_rank and cache_stride must be >= 0, inference_steps >= 1")


class SandboxRefiner(LatentRefiner):
    """SD 1.5 + AnimateDiff refiner (see the module docstring).

    Args:
        settings: the [model] table as `SandboxSettings`.
        ctx: the run's model context (frames, size).

    Raises:
        MorphgsError: frames past the adapter's range; ModelFolderError / FileNotFoundError:
            bad model folders (named).
    """

    kind = "sandbox"

    def __init__(self, settings: SandboxSettings, ctx: ModelContext) -> None:
        super().__init__(settings, ctx)
        s = settings
        parts = load_sd15(s.sd15, config_dir=s.sd15_config, variant=s.variant)
        adapter = load_motion_adapter(s.motion_adapter, config_dir=s.motion_adapter_config, variant=s.variant)
        max_frames = int(adapter.config.motion_max_seq_length)
        if ctx.frames > max_frames:
            raise MorphgsError(f"sandbox: {ctx.frames} frames per clip, but the motion adapter's positional "
                               f"encoding covers {max_frames} (motion_max_seq_length)")
        self.unet = build_motion_unet(parts.unet, adapter, in_channels=s.conv_in_channels,
                                      cond_scale=s.conv_in_cond_scale, lora_rank=s.lora_rank,
                                      lora_alpha=s.lora_alpha, lora_dropout=s.lora_dropout,
                                      lora_targets=s.lora_targets)
        for p in self.unet.parameters():
            if not p.requires_grad:
                p.data = p.data.to(self._weight_dtype)
        if s.gradient_checkpointing and ctx.training:
            self.unet.enable_gradient_checkpointing()
        self.latent_channels = int(parts.vae.config.latent_channels)
        self.latent_norm = LatentNorm.from_vae_config(parts.vae.config)
        self._vae_spatial = 2 ** (len(parts.vae.config.block_out_channels) - 1)
        self.check_context(ctx, multiple=self._spatial_multiple())
        self.scheduler = objectives.ddpm_scheduler()
        self._aux["codec"] = SDCodec(parts.vae)
        self._aux["text"] = (parts.tokenizer, parts.text_encoder)
        self._text_tokens = int(parts.tokenizer.model_max_length)

    # ---- pieces for the base class ----------------------------------------------------------
    def _reload(self) -> Any:
        s = self.settings
        return load_sd15(s.sd15, config_dir=s.sd15_config, variant=s.variant)

    def _load_codec(self) -> SDCodec:
        return SDCodec(self._reload().vae)

    def _load_text(self) -> tuple[Any, Any]:
        parts = self._reload()
        return parts.tokenizer, parts.text_encoder

    def _component_ids(self) -> tuple[str, str]:
        root = Path(self.settings.sd15).expanduser()
        if root.is_dir():
            return (f"AutoencoderKL:{files_fingerprint(root / 'vae')}",
                    f"CLIPTextModel:{files_fingerprint(root / 'text_encoder')}")
        single = files_fingerprint(root)
        return f"AutoencoderKL:{single}", f"CLIPTextModel:{single}"

    def _spatial_multiple(self) -> int:
        # the VAE's factor times the UNet's total downsampling (odd latent sizes would need
        # the UNet's forward_upsample_size path; keep windows regular instead)
        return self._vae_spatial * 2 ** (len(self.unet.config.down_block_types) - 1)

    def param_groups(self, *, lr: float, weight_decay: float) -> list[dict[str, Any]]:
        """AdamW groups: LoRA weights at ``lr``, conv_in at ``conv_in_lr`` (default ``lr``)."""
        named = [(n, p) for n, p in self.unet.named_parameters() if p.requires_grad]
        lora = [p for n, p in named if not n.startswith("conv_in.")]
        conv = [p for n, p in named if n.startswith("conv_in.")]
        groups = [{"params": lora, "lr": lr, "weight_decay": weight_decay}] if lora else []
        return groups + [{"params": conv, "lr": self.settings.conv_in_lr or lr, "weight_decay": weight_decay}]

    def _unet(self, x: torch.Tensor, cond: torch.Tensor, t: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        f = x.shape[2]
        inp = torch.cat([x, cond.to(x.dtype)], dim=1)
        with self.autocast(x.device):
            # UNetMotionModel wants the text per frame: (B * F, L, D)
            return self.unet(inp, t, text.repeat_interleave(f, dim=0)).sample

    def _denoise_loss(self, target: torch.Tensor, cond: torch.Tensor, text: torch.Tensor,
                      generator: torch.Generator | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        noisy, eps, t = objectives.ddpm_inputs(self.scheduler, target.float(), generator=generator)
        pred = self._unet(noisy, cond, t, text)
        loss = F.mse_loss(pred.float(), eps.float())
        return loss, {"mse": loss.detach(), "timestep": t.float().mean()}

    def _sample(self, cond: torch.Tensor, text: torch.Tensor, *, steps: int,
                generator: torch.Generator | None) -> torch.Tensor:
        sched = objectives.ddim_scheduler(self.scheduler) if self.settings.sampler == "ddim" \
            else objectives.ddpm_scheduler()
        shape = (cond.shape[0], self.latent_channels, *cond.shape[2:])
        return objectives.sample_epsilon(lambda x, t: self._unet(x, cond, t, text), sched, shape, steps=steps,
                                         generator=generator, device=cond.device)
