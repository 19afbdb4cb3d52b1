"""`tiny`: a from-scratch spatio-temporal refiner small enough to train on a CPU in minutes.

A residual UNet over frames (2.8 M parameters with the default config):

- each frame is folded into a half-resolution tensor of 12 channels (pixel-unshuffle by 2), so
  the first convolutions run on a quarter of the pixels without squeezing any pixel away (a
  fold by 4 into 32 channels learnt visibly slower: 48 values per block through 32 features);
- five levels (16, 32, 64, 128, 256 channels at 1/2 .. 1/32 resolution) of (2+1)D residual
  blocks: a 3x3 convolution within each frame, then a 3-tap convolution across frames (temporal
  mixing); every level costs about the same (twice the channels on a quarter of the pixels);
- temporal self-attention at the lowest resolution (every pixel attends over the clip's frames);
- additive skips, nearest upsampling, and a zero-initialised head that predicts a residual at
  full resolution (pixel-shuffle), so an untrained model returns its input and training starts
  from "change nothing".
- optional clean reference frames (Difix-style): encoded by their own stem, averaged, and added
  to every frame's features through a zero-initialised projection.

Convolutions are 2D over (batch x frames) and temporal ones 2D over (frames x pixels), which use
the fast oneDNN kernels on CPUs (PyTorch's 3D CPU convolution is an order of magnitude slower).

Objective: `l1 * L1 + l2 * MSE + ssim * (1 - SSIM) + lpips * LPIPS` on [0, 1] images (defaults:
L1 + (1 - SSIM)), with SSIM and LPIPS (AlexNet or VGG, offline weights) from `morphgs.metrics`.
The SSIM term is 3DGS training's (`ssim_3dgs`: zero padding; on CPUs the fit's native kernel,
about 10x faster than the evaluation SSIM's matrix blur, a quarter of a step less at 128x128)
unless `ssim_variant = "torchmetrics"` (`ssim`, the evaluation convention, reflect padding).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from morphgs.models.base import ModelContext, Refiner
from morphgs.configfile import config_from_dict
from morphgs.models.registry import register_model

__all__ = ["TinyConfig", "TinyNet", "TinyRefiner", "build", "count_parameters"]


@dataclass(frozen=True)
class TinyConfig:
    """The `[model]` section of a tiny run config (configs/tiny.toml documents every key)."""

    channels: tuple[int, ...] = (16, 32, 64, 128, 256)
    blocks: tuple[int, ...] = (1, 1, 1, 1, 2)
    unshuffle: int = 2
    temporal_kernel: int = 3
    attention_heads: int = 4
    groups: int = 8
    l1: float = 1.0
    l2: float = 0.0
    ssim: float = 1.0
    lpips: float = 0.0
    lpips_net: str = "alex"
    ssim_variant: str = "3dgs"

    def __post_init__(self) -> None:
        if len(self.channels) != len(self.blocks) or not self.channels:
            raise ValueError(f"channels and blocks need one entry per level, got {self.channels}, {self.blocks}")
        if any(c < 1 or c % self.groups for c in self.channels):
            raise ValueError(f"channels must be positive multiples of groups={self.groups}, got {self.channels}")
        if any(b < 1 for b in self.blocks):
            raise ValueError(f"blocks must be >= 1 per level, got {self.blocks}")
        if self.unshuffle < 1 or self.temporal_kernel < 1 or self.temporal_kernel % 2 == 0:
            raise ValueError("unshuffle must be >= 1 and temporal_kernel odd and >= 1")
        if self.attention_heads < 0 or (self.attention_heads and self.channels[-1] % self.attention_heads):
            raise ValueError(f"attention_heads must divide the last channel count {self.channels[-1]}")
        if self.lpips_net not in ("alex", "vgg"):
            raise ValueError(f"lpips_net must be alex or vgg, got {self.lpips_net!r}")
        if self.ssim_variant not in ("3dgs", "torchmetrics"):
            raise ValueError(f"ssim_variant must be 3dgs or torchmetrics, got {self.ssim_variant!r}")
        if min(self.l1, self.l2, self.ssim, self.lpips) < 0 or self.l1 + self.l2 + self.ssim + self.lpips <= 0:
            raise ValueError("loss weights l1, l2, ssim, lpips must be >= 0 and not all zero")

    @property
    def size_multiple(self) -> int:
        return self.unshuffle * 2 ** (len(self.channels) - 1)


class _TemporalConv(nn.Module):
    """A k-tap convolution across frames of (B*F, C, H, W) features (as a 2D conv over (F, H*W))."""

    def __init__(self, channels: int, kernel: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, (kernel, 1), padding=(kernel // 2, 0))

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        bf, c, h, w = x.shape
        t = x.reshape(bf // frames, frames, c, h * w).transpose(1, 2)
        y = self.conv(t)
        return y.transpose(1, 2).reshape(bf, c, h, w)


class _Block(nn.Module):
    """(2+1)D residual block: GN-SiLU-conv3x3 (per frame), GN-SiLU-temporal conv, plus the input."""

    def __init__(self, channels: int, cfg: TinyConfig) -> None:
        super().__init__()
        self.norm1 = nn.GroupNorm(cfg.groups, channels)
        self.spatial = nn.Conv2d(channels, channels, 3, padding=1)
        self.norm2 = nn.GroupNorm(cfg.groups, channels)
        self.temporal = _TemporalConv(channels, cfg.temporal_kernel)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        h = self.spatial(F.silu(self.norm1(x)))
        h = self.temporal(F.silu(self.norm2(h)), frames)
        return x + h


class _TemporalAttention(nn.Module):
    """Self-attention across frames at every pixel, residual."""

    def __init__(self, channels: int, heads: int, groups: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm = nn.GroupNorm(groups, channels)
        self.qkv = nn.Linear(channels, 3 * channels)
        self.out = nn.Linear(channels, channels)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        bf, c, h, w = x.shape
        b = bf // frames
        t = self.norm(x).reshape(b, frames, c, h * w).permute(0, 3, 1, 2).reshape(b * h * w, frames, c)
        q, k, v = self.qkv(t).reshape(b * h * w, frames, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b * h * w, frames, c)
        y = self.out(a).reshape(b, h * w, frames, c).permute(0, 2, 3, 1).reshape(bf, c, h, w)
        return x + y


class _Stage(nn.Module):
    """Blocks applied one after the other (each needs the frame count)."""

    def __init__(self, blocks: list[_Block]) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        for blk in self.blocks:
            x = blk(x, frames)
        return x


def _zero(conv: nn.Conv2d) -> nn.Conv2d:
    """A convolution initialised to output zeros."""
    nn.init.zeros_(conv.weight)
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)
    return conv


class TinyNet(nn.Module):
    """The network: (B, 3, F, H, W) in [-1, 1] (+ optional (B, 3, R, H, W) references) -> same."""

    def __init__(self, cfg: TinyConfig, *, reference: bool) -> None:
        super().__init__()
        self.cfg = cfg
        r, ch = cfg.unshuffle, cfg.channels
        self.stem = nn.Conv2d(3 * r * r, ch[0], 3, padding=1)
        self.reference = reference
        if reference:
            self.ref_stem = nn.Conv2d(3 * r * r, ch[0], 3, padding=1)
            self.ref_proj = _zero(nn.Conv2d(ch[0], ch[0], 1))
        self.encoder = nn.ModuleList([_Stage([_Block(c, cfg) for _ in range(n)]) for c, n in zip(ch, cfg.blocks)])
        self.down = nn.ModuleList([nn.Conv2d(a, b, 3, stride=2, padding=1) for a, b in zip(ch[:-1], ch[1:])])
        self.attention = _TemporalAttention(ch[-1], cfg.attention_heads, cfg.groups) if cfg.attention_heads else None
        self.up = nn.ModuleList([nn.Conv2d(b, a, 1) for a, b in zip(ch[:-1], ch[1:])])
        self.decoder = nn.ModuleList([_Block(c, cfg) for c in ch[:-1]])
        self.head_norm = nn.GroupNorm(cfg.groups, ch[0])
        self.head = _zero(nn.Conv2d(ch[0], 3 * r * r, 3, padding=1))

    def _fold(self, x: torch.Tensor) -> torch.Tensor:
        b, c, f, h, w = x.shape
        return F.pixel_unshuffle(x.transpose(1, 2).reshape(b * f, c, h, w), self.cfg.unshuffle)

    def forward(self, x: torch.Tensor, reference: torch.Tensor | None = None) -> torch.Tensor:
        b, c, f, h, w = x.shape
        m = self.cfg.size_multiple
        if h % m or w % m:
            raise ValueError(f"tiny needs H and W divisible by {m}, got {h}x{w}")
        feats = self.stem(self._fold(x))
        if self.reference:
            if reference is None:
                raise ValueError("this tiny model was trained with reference frames; pass reference=")
            rf = self.ref_stem(self._fold(reference))
            rf = rf.reshape(b, reference.shape[2], *rf.shape[1:]).mean(dim=1)
            feats = feats + self.ref_proj(rf).repeat_interleave(f, dim=0)
        skips = []
        for i, stage in enumerate(self.encoder):
            feats = stage(feats, f)
            if i < len(self.down):
                skips.append(feats)
                feats = self.down[i](feats)
        if self.attention is not None:
            feats = self.attention(feats, f)
        for i in reversed(range(len(self.up))):
            feats = F.interpolate(self.up[i](feats), scale_factor=2.0, mode="nearest") + skips[i]
            feats = self.decoder[i](feats, f)
        res = self.head(F.silu(self.head_norm(feats)))
        res = F.pixel_shuffle(res, self.cfg.unshuffle).reshape(b, f, c, h, w).transpose(1, 2)
        return x + res.to(x.dtype)


def _frames(x: torch.Tensor) -> torch.Tensor:
    """(B, C, F, H, W) in [-1, 1] -> (B, F, C, H, W) in [0, 1], float32 (the metrics' layout)."""
    return ((x.float() + 1.0) * 0.5).transpose(1, 2)


class TinyRefiner(Refiner):
    """The registered `tiny` model: TinyNet plus its L1 + SSIM objective."""

    def __init__(self, cfg: TinyConfig, ctx: ModelContext) -> None:
        super().__init__()
        self.cfg = cfg
        self.window = ctx.frames
        self.size_multiple = cfg.size_multiple
        self.net = TinyNet(cfg, reference=ctx.reference > 0)
        if cfg.lpips > 0 and ctx.training:
            from morphgs.metrics import lpips_model

            lpips_model(cfg.lpips_net)  # load the frozen network now: missing weights fail here, not at step 1

    def forward(self, batch: Mapping[str, Any], *,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        from morphgs.metrics import lpips, ssim, ssim_3dgs

        corrupted, clean = batch["corrupted"], batch["clean"]
        pred = self.net(corrupted, batch.get("reference"))
        # the losses in float32 even under bf16 autocast: SSIM's E[x^2] - E[x]^2 cancels badly in bf16
        with torch.autocast(pred.device.type, enabled=False):
            p, t = _frames(pred), _frames(clean)
            l1 = (p - t).abs().mean()
            loss = self.cfg.l1 * l1
            logs = {"l1": l1.detach(), "l1_input": (_frames(corrupted) - t).abs().mean().detach()}
            if self.cfg.l2 > 0:
                l2 = (p - t).square().mean()
                loss = loss + self.cfg.l2 * l2
                logs["l2"] = l2.detach()
            if self.cfg.ssim > 0:
                sfn = ssim_3dgs if self.cfg.ssim_variant == "3dgs" else ssim
                s = sfn(p.flatten(0, 1), t.flatten(0, 1))
                loss = loss + self.cfg.ssim * (1.0 - s)
                logs["ssim"] = s.detach()
            if self.cfg.lpips > 0:
                lp = lpips(p.flatten(0, 1), t.flatten(0, 1), net=self.cfg.lpips_net)
                loss = loss + self.cfg.lpips * lp
                logs["lpips"] = lp.detach()
        return loss, logs

    @torch.no_grad()
    def refine(self, corrupted: torch.Tensor, *, reference: torch.Tensor | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        return self.net(corrupted, reference).clamp(-1.0, 1.0)


@register_model("tiny", config="tiny.toml",
                description="from-scratch (2+1)D residual UNet, ~3M parameters; trains on a CPU in minutes")
def build(model_config: dict[str, Any], ctx: ModelContext) -> TinyRefiner:
    """Build `tiny` from the `[model]` section of a run config."""
    cfg = config_from_dict(TinyConfig, model_config, section="model")
    return TinyRefiner(cfg, ctx)



def count_parameters(model: nn.Module) -> int:
    """Number of parameters of a module."""
    return sum(p.numel() for p in model.parameters())
