"""The `controlnet` refiner: frozen Wan2.2 DiT (one or two experts) + trainable dilated ControlNet,
flow matching.

Training input: cached VAE posteriors of clean (target) and corrupted (control) clips (49 frames
at 832x480 in the paper) and a cached UMT5 prompt embedding. Each step draws a fresh target latent,
a noise level sigma (configurable density and shift, optionally restricted to one A14B expert's
range), forms ``x_t = (1 - sigma) x_0 + sigma * noise`` and regresses ``noise - x_0`` with the
expert that owns that noise level, the ControlNet's residuals (from the corrupted latents) added
after its blocks 0, 3, ..., 21. Only the ControlNet trains. Inference integrates the flow from
noise in 50 Euler steps (switching experts at the boundary), then decodes with the Wan VAE.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from morphgs._core import MorphgsError
from morphgs.diffusion import objectives
from morphgs.diffusion.codecs import LatentNorm, WanCodec, files_fingerprint
from morphgs.diffusion.controlnet import DilatedControlNet, controlled_forward
from morphgs.diffusion.folders import DIFFUSERS, read_json, require_folder
from morphgs.diffusion.refiner import DTYPES, LatentRefiner
from morphgs.diffusion.text import DEFAULT_PROMPT
from morphgs.models.base import ModelContext
from morphgs.diffusion.wan import WAN_PARTS, expert_index, timestep_input

__all__ = ["ControlNetRefiner", "ControlNetSettings"]

_EXPERT_RANGES = ("both", "high", "low")


@dataclass(frozen=True)
class ControlNetSettings:
    """The `[model]` table of a controlnet config (configs/controlnet.toml documents every key);
    defaults are the paper's. Frames and clip size come from the run's [data] table.

    Attributes:
        wan: local Wan folder in diffusers layout (Wan2.2 T2V-A14B in the paper; TI2V-5B works).
        variant: weight variant of its files, or None.
        boundary_ratio: A14B expert switch; None reads model_index.json (0.875 for T2V-A14B).
        train_experts: which noise range trains: "both", "high" (sigma >= boundary, the
            high-noise expert) or "low" (as DiffSynth trains the A14B experts one at a time).
        controlnet_blocks, controlnet_stride: 8 blocks copied from base blocks 0, 3, ..., 21.
        controlnet_source: expert the blocks are copied from ("transformer" = high-noise,
            "transformer_2" = low-noise).
        conditioning_scale: factor on the residuals.
        shift, timestep_sampling, logit_mean, logit_std, mode_scale, loss_weighting: flow
            matching (see `morphgs.diffusion.objectives.FlowSettings`).
        prompt, captions, text_tokens: prompt (or per-pair captions file) and UMT5 length (512).
        weight_dtype, gradient_checkpointing: frozen-weight dtype and block recomputation.
        cache_dir, cache_dtype, cache_stride, rebuild_cache, condition: as for the sandbox.
        inference_steps: Euler steps in refine (50).
    """

    wan: str = ""
    variant: str | None = None
    boundary_ratio: float | None = None
    train_experts: str = "both"
    controlnet_blocks: int = 8
    controlnet_stride: int = 3
    controlnet_source: str = "transformer"
    conditioning_scale: float = 1.0
    shift: float = 5.0
    timestep_sampling: str = "uniform"
    logit_mean: float = 0.0
    logit_std: float = 1.0
    mode_scale: float = 1.29
    loss_weighting: str = "none"
    prompt: str = DEFAULT_PROMPT
    captions: str | None = None
    text_tokens: int = 512
    weight_dtype: str = "bfloat16"
    gradient_checkpointing: bool = True
    cache_dir: str | None = None
    cache_dtype: str = "float32"
    cache_stride: int = 0
    rebuild_cache: bool = False
    condition: str = "mean"
    inference_steps: int = 50

    def __post_init__(self) -> None:
        if not self.wan:
            raise ValueError("wan (the local Wan model folder) is not set")
        if self.weight_dtype not in DTYPES:
            raise ValueError(f"weight_dtype {self.weight_dtype!r} is not one of {', '.join(DTYPES)}")
        if self.train_experts not in _EXPERT_RANGES:
            raise ValueError(f"train_experts {self.train_experts!r} is not one of {', '.join(_EXPERT_RANGES)}")
        if self.controlnet_source not in ("transformer", "transformer_2"):
            raise ValueError(f"controlnet_source {self.controlnet_source!r} is not 'transformer' or 'transformer_2'")
        if self.condition not in ("mean", "sample"):
            raise ValueError(f"condition {self.condition!r} is not 'mean' or 'sample'")
        if self.boundary_ratio is not None and not 0.0 < self.boundary_ratio < 1.0:
            raise ValueError(f"boundary_ratio {self.boundary_ratio} is not in (0, 1)")
        if self.inference_steps < 1 or self.text_tokens < 1 or self.cache_stride < 0:
            raise ValueError("inference_steps and text_tokens must be >= 1, cache_stride >= 0")
        self.flow()  # checks the flow-matching options

    def flow(self) -> objectives.FlowSettings:
        return objectives.FlowSettings(shift=self.shift, sampling=self.timestep_sampling,
                                       logit_mean=self.logit_mean, logit_std=self.logit_std,
                                       mode_scale=self.mode_scale, weighting=self.loss_weighting)


class ControlNetRefiner(LatentRefiner):
    """Wan DiT + dilated ControlNet refiner (see the module docstring).

    Args:
        settings: the [model] table as `ControlNetSettings`.
        ctx: the run's model context.

    Raises:
        MorphgsError: settings that do not fit the folder; ModelFolderError / FileNotFoundError:
            bad model folder (named).
    """

    kind = "controlnet"
    _text_masked = True

    def __init__(self, settings: ControlNetSettings, ctx: ModelContext) -> None:
        super().__init__(settings, ctx)
        s = settings
        from diffusers import WanTransformer3DModel

        root = require_folder(s.wan, WAN_PARTS, what="Wan model folder", variant=s.variant)
        index = read_json(root / "model_index.json", what="Wan model_index.json") \
            if (root / "model_index.json").is_file() else {}
        names = ["transformer", "transformer_2"] if (root / "transformer_2").is_dir() else ["transformer"]
        ratio = s.boundary_ratio if s.boundary_ratio is not None else index.get("boundary_ratio")
        if len(names) == 2 and ratio is None:
            raise MorphgsError(f"Wan model folder {root}: two experts but no boundary_ratio "
                               "(in model_index.json or the [model] table)")
        self.boundary_ratio: float | None = float(ratio) if len(names) == 2 and ratio is not None else None
        self.expand_timesteps = bool(index.get("expand_timesteps", False))
        if s.controlnet_source not in names:
            raise MorphgsError(f"controlnet: controlnet_source {s.controlnet_source!r}, but {root} "
                               f"has only {', '.join(names)}")
        if s.train_experts != "both" and len(names) == 1:
            raise MorphgsError(f"controlnet: train_experts = {s.train_experts!r} needs two experts; {root} has one")
        require_folder(root, {n: DIFFUSERS for n in names}, what="Wan model folder", variant=s.variant)
        vae_cfg = read_json(root / "vae" / "config.json", what="Wan VAE config")
        patch = read_json(root / "transformer" / "config.json", what="Wan transformer config").get("patch_size", [1, 2, 2])
        self._vae_spatial = int(vae_cfg.get("scale_factor_spatial", 8))
        self.check_context(ctx, multiple=self._vae_spatial * int(patch[1]),
                           temporal=int(vae_cfg.get("scale_factor_temporal", 4)))
        # training one expert's noise range loads only that expert (half the A14B weights)
        if ctx.training and s.train_experts != "both":
            self.expert_names = [names[0] if s.train_experts == "high" else names[1]]
        else:
            self.expert_names = names

        def load(name: str) -> Any:
            return WanTransformer3DModel.from_pretrained(root, subfolder=name, torch_dtype=self._weight_dtype,
                                                         local_files_only=True, variant=s.variant)

        self.experts = nn.ModuleList([load(n) for n in self.expert_names])
        self.experts.requires_grad_(False).eval()
        source = (self.experts[self.expert_names.index(s.controlnet_source)]
                  if s.controlnet_source in self.expert_names else load(s.controlnet_source))
        self.controlnet = DilatedControlNet.from_transformer(source, num_blocks=s.controlnet_blocks,
                                                             stride=s.controlnet_stride)
        del source
        for e in self.experts:
            self.controlnet.check_base(e)
        self.latent_norm = LatentNorm.from_vae_config(vae_cfg)
        self.latent_channels = int(self._expert(0).config.out_channels)
        self._root = root
        self._text_tokens = int(s.text_tokens)
        self._checkpointing = bool(s.gradient_checkpointing and ctx.training)
        self.flow = s.flow()
        r = self.boundary_ratio
        self._sigma_range = {"both": (0.0, 1.0), "high": (r or 0.0, 1.0), "low": (0.0, r or 1.0)}[s.train_experts]

    def train(self, mode: bool = True) -> ControlNetRefiner:
        """Train mode reaches only the ControlNet; the frozen experts stay in eval mode."""
        super().train(mode)
        self.experts.eval()
        return self

    def _expert(self, i: int) -> Any:
        return self.experts[i]

    # ---- pieces for the base class ----------------------------------------------------------
    def _load_codec(self) -> WanCodec:
        from diffusers import AutoencoderKLWan

        vae = AutoencoderKLWan.from_pretrained(self._root, subfolder="vae", torch_dtype=torch.float32,
                                               local_files_only=True, variant=self.settings.variant)
        return WanCodec(vae.eval().requires_grad_(False))

    def _load_text(self) -> tuple[Any, Any]:
        from transformers import AutoTokenizer, UMT5EncoderModel

        enc = UMT5EncoderModel.from_pretrained(self._root / "text_encoder", dtype=self._weight_dtype,
                                               local_files_only=True, variant=self.settings.variant)
        tok = AutoTokenizer.from_pretrained(self._root / "tokenizer", local_files_only=True)
        return tok, enc.eval().requires_grad_(False)

    def _component_ids(self) -> tuple[str, str]:
        return (f"AutoencoderKLWan:{files_fingerprint(self._root / 'vae')}",
                f"UMT5EncoderModel:{files_fingerprint(self._root / 'text_encoder')}")

    def _spatial_multiple(self) -> int:
        return self._vae_spatial * int(self._expert(0).config.patch_size[1])

    def param_groups(self, *, lr: float, weight_decay: float) -> list[dict[str, Any]]:
        """AdamW groups: every ControlNet parameter at ``lr``."""
        params = [p for p in self.controlnet.parameters() if p.requires_grad]
        return [{"params": params, "lr": lr, "weight_decay": weight_decay}]

    def velocity(self, expert: int, x: torch.Tensor, t: torch.Tensor, text: torch.Tensor,
                 cond: torch.Tensor) -> torch.Tensor:
        """One expert's flow prediction with the ControlNet's residuals, for timesteps ``t`` (B,)."""
        base = self._expert(expert)
        ts = timestep_input(t, x.shape, tuple(base.config.patch_size), expand=self.expand_timesteps)
        with self.autocast(x.device):
            return controlled_forward(base, self.controlnet, x, ts, text, cond, scale=self.settings.conditioning_scale,
                                      gradient_checkpointing=self._checkpointing and torch.is_grad_enabled())

    def _denoise_loss(self, target: torch.Tensor, cond: torch.Tensor, text: torch.Tensor,
                      generator: torch.Generator | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        b = target.shape[0]
        sigmas = objectives.flow_sigmas(b, self.flow, sigma_range=self._sigma_range, generator=generator,
                                        device=target.device)
        noisy, v_target, t = objectives.flow_inputs(target.float(), sigmas, generator=generator)
        weights = objectives.flow_loss_weights(sigmas, self.flow).to(target.device)
        which = expert_index(t, self.boundary_ratio)
        if len(self.experts) == 1:  # one expert (or one expert's range) loaded
            which = torch.zeros_like(which)
        total = target.new_zeros((), dtype=torch.float32)
        for e in which.unique().tolist():
            m = which == e
            pred = self.velocity(int(e), noisy[m], t[m], text[m], cond[m])
            err = (pred.float() - v_target[m].float()).square().flatten(1).mean(1)
            total = total + (weights[m] * err).sum()
        loss = total / b
        return loss, {"mse": loss.detach(), "sigma": sigmas.mean()}

    def _sample(self, cond: torch.Tensor, text: torch.Tensor, *, steps: int,
                generator: torch.Generator | None) -> torch.Tensor:
        shape = (cond.shape[0], self.latent_channels, *cond.shape[2:])

        # built to train one expert's range (train_experts = "high"/"low"), only that expert is
        # loaded and runs every step: validation previews are then a proxy; `morphgs refine`
        # builds the model for inference, with both experts
        def model(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            e = int(expert_index(t[:1], self.boundary_ratio)[0]) if len(self.experts) == 2 else 0
            return self.velocity(e, x, t, text.to(x.device), cond)

        return objectives.sample_flow(model, shape, steps=steps, shift=self.settings.shift, generator=generator,
                                      device=cond.device)
