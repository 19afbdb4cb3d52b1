"""VAEs as latent codecs: posterior (mean, std) of a clip, latent scaling, decoding.

Two kinds, one interface:

- `SDCodec`: SD 1.5's `AutoencoderKL`, applied frame by frame (latent frames = frames), latents
  scaled by ``scaling_factor`` (0.18215).
- `WanCodec`: Wan's causal 3D `AutoencoderKLWan` (Wan2.1 VAE: 8x spatial, 4x temporal, 16
  channels; Wan2.2 VAE of TI2V-5B: 16x spatial, 48 channels), clips of 4k+1 frames, latents
  normalised per channel with the config's ``latents_mean``/``latents_std`` as the Wan pipelines do.

Clips are (B, 3, F, H, W) in [-1, 1]; latents are (B, C, F', H', W').
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

_MIB = 1 << 20

__all__ = ["LatentNorm", "SDCodec", "WanCodec", "files_fingerprint"]


def files_fingerprint(path: str | os.PathLike[str]) -> str:
    """A cheap identity of a model folder or single file (sha256, 16 hex) without loading it: every
    file's relative name and size, the folder's config.json in full, and the first and last MiB of
    each weight file. Identifies a VAE or text encoder for a cache without reading gigabytes."""
    p = Path(path)
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    h = hashlib.sha256()
    for f in files:
        size = f.stat().st_size
        h.update(f"{f.relative_to(p) if p.is_dir() else f.name}:{size}".encode())
        with open(f, "rb") as fh:
            if f.suffix == ".json" or size <= 2 * _MIB:
                h.update(fh.read())
            else:
                h.update(fh.read(_MIB))
                fh.seek(size - _MIB)
                h.update(fh.read(_MIB))
    return h.hexdigest()[:16]


class LatentNorm:
    """The map between raw VAE latents and the denoiser's latent space, from a VAE config alone
    (no weights): ``x = (z - shift) * scale`` per channel.

    SD's AutoencoderKL: shift ``shift_factor`` (absent for SD 1.5: 0), scale ``scaling_factor``
    (0.18215). Wan's AutoencoderKLWan: shift ``latents_mean``, scale ``1 / latents_std``.
    """

    def __init__(self, shift: Sequence[float], scale: Sequence[float]) -> None:
        self.shift = torch.tensor(list(shift), dtype=torch.float32).view(1, -1, 1, 1, 1)
        self.scale = torch.tensor(list(scale), dtype=torch.float32).view(1, -1, 1, 1, 1)

    @classmethod
    def from_vae_config(cls, config: Mapping[str, Any]) -> LatentNorm:
        """From a VAE's config (a dict or a diffusers FrozenDict)."""
        if config.get("latents_mean") is not None:  # Wan
            std = [float(v) for v in config["latents_std"]]
            return cls([float(v) for v in config["latents_mean"]], [1.0 / v for v in std])
        c = int(config.get("latent_channels", 4))
        shift = float(config.get("shift_factor") or 0.0)
        return cls([shift] * c, [float(config.get("scaling_factor", 0.18215))] * c)

    def normalize(self, z: torch.Tensor) -> torch.Tensor:
        """Raw VAE latents -> the denoiser's latent space."""
        return (z - self.shift.to(z.device, z.dtype)) * self.scale.to(z.device, z.dtype)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        """The denoiser's latents -> raw VAE latents."""
        return x / self.scale.to(x.device, x.dtype) + self.shift.to(x.device, x.dtype)


class SDCodec:
    """SD 1.5's VAE applied per frame.

    Args:
        vae: a diffusers `AutoencoderKL`.
        chunk: frames encoded or decoded at once (memory bound).
    """

    kind = "sd"

    def __init__(self, vae: Any, *, chunk: int = 8) -> None:
        self.vae = vae
        self.chunk = chunk
        self.norm = LatentNorm.from_vae_config(vae.config)
        self.spatial = 2 ** (len(vae.config.block_out_channels) - 1)
        self.channels = int(vae.config.latent_channels)

    def check_clip(self, frames: int, height: int, width: int) -> None:
        """Raise ValueError if a clip size cannot be encoded."""
        if height % self.spatial or width % self.spatial:
            raise ValueError(f"SD VAE: clip size {height}x{width} must be a multiple of {self.spatial}")

    def latent_shape(self, frames: int, height: int, width: int) -> tuple[int, int, int, int]:
        """(C, F', H', W') of a clip's latents."""
        return self.channels, frames, height // self.spatial, width // self.spatial

    def _dtype(self) -> torch.dtype:
        return next(self.vae.parameters()).dtype

    @torch.no_grad()
    def posterior(self, video: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The posterior mean and std (unscaled) of a clip, float32 (B, 4, F, H/8, W/8)."""
        b, _, f, h, w = video.shape
        self.check_clip(f, h, w)
        x = video.permute(0, 2, 1, 3, 4).reshape(b * f, 3, h, w).to(self._dtype())
        means, stds = [], []
        for i in range(0, x.shape[0], self.chunk):
            d = self.vae.encode(x[i:i + self.chunk]).latent_dist
            means.append(d.mean.float())
            stds.append(d.std.float())
        mean, std = torch.cat(means), torch.cat(stds)
        shape = (b, f) + tuple(mean.shape[1:])
        return (mean.reshape(shape).permute(0, 2, 1, 3, 4).contiguous(),
                std.reshape(shape).permute(0, 2, 1, 3, 4).contiguous())

    def normalize(self, z: torch.Tensor) -> torch.Tensor:
        """Raw VAE latents -> the diffusion model's latent space (``z * 0.18215`` for SD 1.5)."""
        return self.norm.normalize(z)

    def denormalize(self, latents: torch.Tensor) -> torch.Tensor:
        """The diffusion model's latents -> raw VAE latents."""
        return self.norm.denormalize(latents)

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """Normalised latents (B, 4, F, h, w) -> clip (B, 3, F, 8h, 8w) in [-1, 1], float32."""
        b, c, f, h, w = latents.shape
        z = self.denormalize(latents).permute(0, 2, 1, 3, 4).reshape(b * f, c, h, w).to(self._dtype())
        out = torch.cat([self.vae.decode(z[i:i + self.chunk]).sample.float() for i in range(0, b * f, self.chunk)])
        out = out.reshape((b, f) + tuple(out.shape[1:])).permute(0, 2, 1, 3, 4)
        return out.clamp(-1, 1).contiguous()


class WanCodec:
    """Wan's causal video VAE.

    Args:
        vae: a diffusers `AutoencoderKLWan`.
    """

    kind = "wan"

    def __init__(self, vae: Any) -> None:
        self.vae = vae
        cfg = vae.config
        self.temporal = int(cfg.scale_factor_temporal)
        self.spatial = int(cfg.scale_factor_spatial)
        self.channels = int(cfg.z_dim)
        self.norm = LatentNorm.from_vae_config(cfg)

    def check_clip(self, frames: int, height: int, width: int) -> None:
        """Raise ValueError if a clip size cannot be encoded (frames 4k+1, sides multiples of the
        spatial factor)."""
        if (frames - 1) % self.temporal:
            raise ValueError(f"Wan VAE: {frames} frames; clips need {self.temporal}k+1 frames (49, 81, ...)")
        if height % self.spatial or width % self.spatial:
            raise ValueError(f"Wan VAE: clip size {height}x{width} must be a multiple of {self.spatial}")

    def latent_shape(self, frames: int, height: int, width: int) -> tuple[int, int, int, int]:
        """(C, F', H', W') of a clip's latents."""
        return (self.channels, (frames - 1) // self.temporal + 1, height // self.spatial, width // self.spatial)

    def _dtype(self) -> torch.dtype:
        return next(self.vae.parameters()).dtype

    @torch.no_grad()
    def posterior(self, video: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The posterior mean and std (unnormalised) of a clip, float32 (B, z, F', H', W')."""
        self.check_clip(*video.shape[2:])
        d = self.vae.encode(video.to(self._dtype())).latent_dist
        return d.mean.float().contiguous(), d.std.float().contiguous()

    def normalize(self, z: torch.Tensor) -> torch.Tensor:
        """Raw VAE latents -> the transformer's latent space, ``(z - mean) / std`` per channel."""
        return self.norm.normalize(z)

    def denormalize(self, latents: torch.Tensor) -> torch.Tensor:
        """The transformer's latents -> raw VAE latents."""
        return self.norm.denormalize(latents)

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """Normalised latents -> clip (B, 3, F, H, W) in [-1, 1], float32."""
        z = self.denormalize(latents.float()).to(self._dtype())
        return self.vae.decode(z).sample.float().clamp(-1, 1)
