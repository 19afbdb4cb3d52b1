"""What the two latent-diffusion refiners share, as a `morphgs.models.Refiner`: the latent + text
cache (`prepare_data`), fresh posterior samples each step (`forward`), the refine pipeline
(encode the corrupted window, denoise from noise conditioned on it, decode) and trainable-only
checkpoints (the `Refiner` default).

The VAE, the text encoder and the tokenizer are *not* registered submodules: `accelerate.prepare`
(and DDP/FSDP) sees only the denoising network, and the encoders are loaded when a cache is built
or a clip is refined (UMT5-XXL alone is 11 GB in bf16). The prompt embedding is kept once
computed, so the text encoder is dropped after the cache is built.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from morphgs._core import MorphgsError
from morphgs.diffusion.latent_cache import CacheKey, build_cache, fingerprint
from morphgs.diffusion.text import load_captions
from morphgs.models.base import ModelContext, Refiner

__all__ = ["DTYPES", "LatentRefiner", "randn"]

DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


def randn(shape: Sequence[int], generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """Standard normal float32 noise from ``generator`` (on its own device), moved to ``device``."""
    if generator is None:
        return torch.randn(tuple(shape), device=device)
    return torch.randn(tuple(shape), generator=generator, device=generator.device).to(device)


class LatentRefiner(Refiner):
    """Base class of `SandboxRefiner` and `ControlNetRefiner`.

    Subclass contract: ``kind``; ``settings`` (prompt, captions, cache_dir, cache_dtype,
    cache_stride, rebuild_cache, condition, inference_steps, weight_dtype); ``latent_norm`` (a
    `LatentNorm` from the VAE config) and ``latent_channels``; `_load_codec()`, `_load_text()`,
    `_component_ids()`, `_text_tokens`, `_text_masked`, `_spatial_multiple()`,
    `_denoise_loss(target, cond, text, generator)` returning (loss, logs) and
    `_sample(cond, text, steps, generator)`.
    """

    kind = "latent"
    _text_masked = False
    _text_tokens = 77
    _aux: dict[Any, Any]  # set in __init__ through __dict__: not a submodule
    latent_norm: Any  # LatentNorm
    latent_channels: int

    def __init__(self, settings: Any, ctx: ModelContext) -> None:
        super().__init__()
        if ctx.reference:
            raise MorphgsError(f"{self.kind}: the model takes no clean reference frames ([data] reference = "
                               f"{ctx.reference}; set it to 0)")
        self.settings = settings
        self.window = int(ctx.frames)
        self._weight_dtype = DTYPES[settings.weight_dtype]
        self.__dict__["_aux"] = {}  # encoders and cached prompt embeddings: not submodules

    # ---- what subclasses provide ------------------------------------------------------------
    def _load_codec(self) -> Any:
        raise NotImplementedError

    def _load_text(self) -> tuple[Any, Any]:
        raise NotImplementedError

    def _component_ids(self) -> tuple[str, str]:
        """Identities of the VAE and the text encoder for cache keys (cheap, no loading)."""
        raise NotImplementedError

    def _spatial_multiple(self) -> int:
        raise NotImplementedError

    def _denoise_loss(self, target: torch.Tensor, cond: torch.Tensor, text: torch.Tensor,
                      generator: torch.Generator | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        raise NotImplementedError

    def _sample(self, cond: torch.Tensor, text: torch.Tensor, *, steps: int,
                generator: torch.Generator | None) -> torch.Tensor:
        raise NotImplementedError

    @property
    def size_multiple(self) -> int:  # type: ignore[override]
        """H and W of refined windows must be multiples of this (morphgs refine pads)."""
        return self._spatial_multiple()

    # ---- encoders ---------------------------------------------------------------------------
    def _device(self) -> torch.device:
        for p in self.parameters():
            return p.device
        return torch.device("cpu")

    def codec(self, device: torch.device | None = None) -> Any:
        """The VAE as a latent codec (loaded on first use), on ``device`` (default: the
        network's)."""
        if "codec" not in self._aux:
            self._aux["codec"] = self._load_codec()
        codec = self._aux["codec"]
        codec.vae.to(device or self._device())
        return codec

    def encode_text(self, prompts: Sequence[str], *, device: torch.device | None = None) -> torch.Tensor:
        """Prompt embeddings (P, L, D), float32 on the CPU (loads the text encoder if needed and
        runs it on ``device``, default the network's)."""
        from morphgs.diffusion.text import encode_prompts

        if "text" not in self._aux:
            self._aux["text"] = self._load_text()
        tok, enc = self._aux["text"]
        enc.to(device or self._device())
        return encode_prompts(tok, enc, prompts, max_length=self._text_tokens, masked=self._text_masked)

    def prompt_embedding(self, prompt: str) -> torch.Tensor:
        """One prompt's embedding (L, D), computed once and kept."""
        key = ("prompt", prompt)
        if key not in self._aux:
            self._aux[key] = self.encode_text([prompt])[0]
        return self._aux[key]

    def release_text_encoder(self) -> None:
        """Drop the text encoder and tokenizer (reloaded if another prompt is ever needed)."""
        self._aux.pop("text", None)

    # ---- the latent + text cache ------------------------------------------------------------
    def cache_dir(self, dataset: Any, ctx: ModelContext) -> Path:
        """The cache folder: ``cache_dir`` of the [model] table, else the run's cache folder,
        else ``DATA/.latents``; one subfolder per model kind and split."""
        base = self.settings.cache_dir or ctx.cache_dir or Path(dataset.root) / ".latents"
        return Path(base) / f"{self.kind}-{dataset.split}"

    def cache_key(self, dataset: Any) -> CacheKey:
        """The key a cache of this dataset must have for this model and settings."""
        from morphgs.diffusion.data import dataset_fingerprint

        s = self.settings
        vae_id, text_id = self._component_ids()
        captions = load_captions(s.captions) if s.captions else None
        win = dataset.window(0, None)
        return CacheKey(
            model=self.kind, vae=vae_id, text_encoder=text_id, height=int(win.height), width=int(win.width),
            frames=int(dataset.frames), stride=int(s.cache_stride or dataset.frames), dtype=s.cache_dtype,
            dataset=dataset_fingerprint(dataset), split=str(dataset.split),
            prompts=fingerprint({"prompt": s.prompt, "captions": captions}), text_tokens=int(self._text_tokens),
        )

    def prepare_data(self, dataset: Any, *, ctx: ModelContext, accelerator: Any = None) -> Any:
        """Encode the dataset's windows once into the latent + text cache and return the Dataset
        `forward` reads (same keys and length as ``dataset``).

        The main process encodes (its peers wait, then open the finished cache). A cache built
        for another VAE, text encoder, size, frame count, stride, dataset or prompt is refused
        (`LatentCacheError` naming each difference) unless ``rebuild_cache`` is set.

        Raises:
            LatentCacheError: a stale or damaged cache. MorphgsError: clips the VAE cannot take.
        """
        from morphgs.diffusion.data import LatentPairs, cache_windows, window_sources

        s = self.settings
        if not hasattr(dataset, "records") or not hasattr(dataset, "window"):
            raise MorphgsError(f"{self.kind}: trains on a curated folder's latents ([data] live = false); "
                               f"live pairs ({type(dataset).__name__}) cannot be latent-cached")
        win = dataset.window(0, None)
        self.check_clip_size(dataset.frames, win.height, win.width)
        stride = int(s.cache_stride or dataset.frames)
        windows = cache_windows(dataset, stride=stride)
        key = self.cache_key(dataset)
        root = self.cache_dir(dataset, ctx)
        captions = load_captions(s.captions) if s.captions else None
        sources = window_sources(dataset, windows, prompt=s.prompt, captions=captions)
        # encode on the accelerator's device (prepare_data runs before accelerate moves the model)
        device = accelerator.device if accelerator is not None else self._device()
        first = accelerator.main_process_first() if accelerator is not None else contextlib.nullcontext()
        with first:
            # the VAE and the text encoder load only if the cache has to be built
            cache = build_cache(root, key, sources,
                                posterior=lambda clip: self.codec(device).posterior(clip.to(device)),
                                encode_text=lambda prompts: self.encode_text(prompts, device=device),
                                rebuild=bool(s.rebuild_cache))
        if s.prompt in cache.prompts:  # validation's refine reuses it: no text encoder reload
            self._aux[("prompt", s.prompt)] = cache.text[cache.prompts.index(s.prompt)]
        self.release_text_encoder()
        return LatentPairs(cache, [r.pair_id for r in dataset.records], train=bool(dataset.train),
                           centres=[w.start for w in (dataset.window(i, None) for i in range(len(dataset)))])

    def check_context(self, ctx: ModelContext, *, multiple: int, temporal: int = 1) -> None:
        """Refuse a run geometry the model cannot take, before any heavy loading.

        Raises:
            MorphgsError: [data] frames not ``temporal * k + 1`` (when temporal > 1), or a size
                whose sides are not multiples of ``multiple``.
        """
        if temporal > 1 and (ctx.frames - 1) % temporal:
            raise MorphgsError(f"{self.kind}: [data] frames = {ctx.frames}; the VAE needs {temporal}k+1 frames "
                               "(49 in the paper, 81, ...)")
        if ctx.size is not None and (ctx.size[0] % multiple or ctx.size[1] % multiple):
            raise MorphgsError(f"{self.kind}: [data] size = {list(ctx.size)}; H and W must be multiples of {multiple}")

    def check_clip_size(self, frames: int, height: int, width: int) -> None:
        """Raise MorphgsError if training windows of this size do not fit the model."""
        m = self._spatial_multiple()
        if height % m or width % m:
            raise MorphgsError(f"{self.kind}: training windows of {height}x{width} (HxW); this model needs "
                               f"multiples of {m} ([data] size / resize)")

    # ---- training ---------------------------------------------------------------------------
    def _draw(self, mean: torch.Tensor, std: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """A fresh posterior sample ``mean + std * noise``, normalised for the denoiser."""
        z = mean.float() + std.float() * randn(mean.shape, generator, mean.device)
        return self.latent_norm.normalize(z)

    def forward(self, batch: Mapping[str, Any], *,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The objective on a batch of cached items: a fresh VAE sample of the clean latents is
        the target, the corrupted latents (posterior mean, or a sample) the condition.

        Args:
            batch: collated `LatentPairs` items.
            generator: every random draw of the step comes from it.

        Returns:
            (float32 scalar loss, logs).
        """
        target = self._draw(batch["clean_mean"], batch["clean_std"], generator)
        if self.settings.condition == "sample":
            cond = self._draw(batch["corrupted_mean"], batch["corrupted_std"], generator)
        else:
            cond = self.latent_norm.normalize(batch["corrupted_mean"].float())
        return self._denoise_loss(target, cond, batch["text"].float(), generator)

    # ---- inference --------------------------------------------------------------------------
    @torch.no_grad()
    def refine(self, corrupted: torch.Tensor, *, reference: torch.Tensor | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Refine one window: encode it, denoise from noise conditioned on its latents in
        ``inference_steps`` steps, decode.

        Args:
            corrupted: (B, 3, F, H, W) in [-1, 1]; H, W multiples of `size_multiple`.
            reference: unused (the model takes no reference frames).
            generator: source of the initial noise.

        Returns:
            (B, 3, F, H, W) in [-1, 1], float32, before colour correction.

        Raises:
            MorphgsError: a size or frame count the VAE and network cannot take.
        """
        codec = self.codec()
        b, _, f, h, w = corrupted.shape
        try:
            codec.check_clip(f, h, w)
        except ValueError as e:
            raise MorphgsError(f"{self.kind} refine: {e}") from None
        self.check_clip_size(f, h, w)
        device = self._device()
        cond = codec.normalize(codec.posterior(corrupted.float().to(device))[0])
        text = self.prompt_embedding(self.settings.prompt).to(device).expand(b, -1, -1)
        latents = self._sample(cond, text, steps=int(self.settings.inference_steps), generator=generator)
        return codec.decode(latents.to(device)).clamp(-1, 1)

    def autocast(self, device: torch.device) -> Any:
        """bf16/fp16 autocast when the frozen weights are stored in that dtype (so the model runs
        whatever the loop's mixed-precision setting); a no-op for float32 weights."""
        if self._weight_dtype == torch.float32:
            return contextlib.nullcontext()
        return torch.autocast(device_type=device.type, dtype=self._weight_dtype)
