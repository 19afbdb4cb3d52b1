"""The latent + text cache: each clip pair is VAE-encoded once per dataset, not once per step.

Layout of a cache folder::

    meta.json                 the key it was built for (below) and the item list
    text.safetensors          "embeddings": (P, L, D), one row per distinct prompt
    items/000000.safetensors  "clean_mean", "clean_std", "corrupted_mean", "corrupted_std"
                              (B=1 dropped: (C, F', H', W') each)

Each item stores the VAE posterior's mean and standard deviation (not one sample), so every
training step draws a fresh ``mean + std * noise``: caching a single sample (as TheDenk's
``prepare_vae_latents.py`` does) would freeze the VAE noise for the whole run.

The key records what the latents depend on: the model kind, the VAE (class and a content hash of
its weights), the text encoder, the clip size and frame count, the window stride, the storage
dtype, the dataset (a hash of its manifest records for the split) and the prompts. Opening a
cache with another key is refused with a `LatentCacheError` naming every field that differs; a
cache is built in a temporary folder and renamed into place, so a killed build never looks
finished. `checksums.json` (morphgs.reliability) records every file's size and sha256; a cache
whose files no longer have their sizes (truncated by a full disk, a crash during a copy) is
reported with a warning and encoded again.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from morphgs._core import MorphgsWarning
from morphgs.diffusion.errors import LatentCacheError
from morphgs.reliability import verify_checksums, write_checksums

__all__ = ["CACHE_VERSION", "CacheKey", "CacheSource", "LatentCache", "build_cache", "fingerprint"]

CACHE_VERSION = 1
_DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
_TENSORS = ("clean_mean", "clean_std", "corrupted_mean", "corrupted_std")


def fingerprint(obj: Any) -> str:
    """sha256 (16 hex) of a JSON-serialisable object (keys sorted)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class CacheKey:
    """What a cache's contents depend on; two runs share a cache only if every field agrees."""

    model: str
    vae: str
    text_encoder: str
    height: int
    width: int
    frames: int
    stride: int
    dtype: str
    dataset: str
    split: str
    prompts: str
    text_tokens: int
    version: int = CACHE_VERSION

    def __post_init__(self) -> None:
        if self.dtype not in _DTYPES:
            raise ValueError(f"latent cache dtype {self.dtype!r} is not one of {', '.join(_DTYPES)}")

    def diff(self, stored: Mapping[str, Any]) -> list[str]:
        """Fields where a stored key differs from this one, as ``field: cache has X, run wants Y``."""
        out = []
        for k, v in asdict(self).items():
            if stored.get(k) != v:
                out.append(f"{k}: cache has {stored.get(k)!r}, this run wants {v!r}")
        return out


@dataclass(frozen=True)
class CacheSource:
    """One clip pair to encode: tensors (3, F, H, W) in [-1, 1] and the prompt to use."""

    pair_id: str
    start: int
    clean: torch.Tensor
    corrupted: torch.Tensor
    prompt: str


class LatentCache:
    """A finished cache folder, opened for reading (use `build_cache` or `LatentCache.open`)."""

    def __init__(self, root: Path, meta: dict[str, Any]) -> None:
        self.root = root
        self.meta = meta
        self.items: list[dict[str, Any]] = meta["items"]
        self.prompts: list[str] = meta["prompts"]
        self._text: torch.Tensor | None = None

    @classmethod
    def open(cls, root: str | os.PathLike[str], key: CacheKey) -> LatentCache | None:
        """Open the cache at ``root`` if it was built for ``key``.

        Returns:
            The cache, or None if there is none at ``root`` yet.

        Raises:
            LatentCacheError: the folder holds a cache for another key (every differing field is
                named), or its meta.json is unreadable.
        """
        r = Path(root)
        meta_path = r / "meta.json"
        if not meta_path.is_file():
            if r.exists() and any(r.iterdir()):
                raise LatentCacheError(f"latent cache {r}: the folder exists but has no meta.json; "
                                       "it is not a morphgs latent cache (delete it or choose another cache_dir)")
            return None
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
            stored = meta["key"]
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise LatentCacheError(f"latent cache {meta_path}: unreadable ({e})") from None
        diffs = key.diff(stored)
        if diffs:
            raise LatentCacheError(
                f"latent cache {r} is stale for this run: " + "; ".join(diffs)
                + ". Delete the folder (or set rebuild_cache = true, or another cache_dir) to re-encode.")
        return cls(r, meta)

    def __len__(self) -> int:
        return len(self.items)

    @property
    def text(self) -> torch.Tensor:
        """All prompt embeddings (P, L, D), float32."""
        if self._text is None:
            path = self.root / "text.safetensors"
            try:
                self._text = load_file(str(path))["embeddings"].float()
            except (OSError, KeyError, RuntimeError, SafetensorError) as e:
                raise LatentCacheError(f"latent cache {path}: unreadable ({e}); delete the cache to rebuild") from None
        return self._text

    def load(self, i: int) -> dict[str, Any]:
        """Item i: the four posterior tensors (float32), its text embedding and its ids.

        Raises:
            LatentCacheError: the item file is missing or damaged.
        """
        rec = self.items[i]
        path = self.root / "items" / rec["file"]
        try:
            data = load_file(str(path))
        except (OSError, ValueError, RuntimeError, SafetensorError) as e:
            raise LatentCacheError(f"latent cache item {path}: unreadable ({e}); delete the cache to rebuild") from None
        missing = [k for k in _TENSORS if k not in data]
        if missing:
            raise LatentCacheError(f"latent cache item {path}: missing tensors {', '.join(missing)}")
        out: dict[str, Any] = {k: data[k].float() for k in _TENSORS}
        out["text"] = self.text[rec["text"]]
        out["pair_id"] = rec["pair_id"]
        out["start"] = rec["start"]
        return out


def _write_item(path: Path, tensors: dict[str, torch.Tensor], dtype: torch.dtype) -> None:
    save_file({k: v.to(dtype).contiguous() for k, v in tensors.items()}, str(path))


def build_cache(root: str | os.PathLike[str], key: CacheKey, sources: Iterable[CacheSource], *,
                posterior: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                encode_text: Callable[[Sequence[str]], torch.Tensor],
                rebuild: bool = False,
                progress: Callable[[int], None] | None = None) -> LatentCache:
    """Open the cache at ``root`` for ``key``, encoding it first if there is none.

    Args:
        root: cache folder.
        key: what the cache must match.
        sources: the clip pairs, in a fixed order (consumed only when a build is needed).
        posterior: clip (1, 3, F, H, W) -> (mean, std) of the VAE posterior.
        encode_text: prompts -> embeddings (P, L, D).
        rebuild: delete a stale cache and encode again instead of refusing it.
        progress: called with the number of items encoded so far.

    Returns:
        The opened cache.

    Raises:
        LatentCacheError: a stale cache is there and ``rebuild`` is False; or no sources.
    """
    r = Path(root)
    try:
        cache = LatentCache.open(r, key)
    except LatentCacheError:
        if not rebuild:
            raise
        shutil.rmtree(r)
        cache = None
    if cache is not None:
        problem = verify_checksums(r, sizes_only=True)
        if problem is None:
            return cache
        warnings.warn(f"latent cache {r} is damaged ({problem}); encoding it again", MorphgsWarning, stacklevel=2)
        shutil.rmtree(r)
    _remove_dead_builds(r)
    tmp = r.with_name(f".{r.name}.building-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    (tmp / "items").mkdir(parents=True)
    try:
        meta = _encode(tmp, key, sources, posterior=posterior, encode_text=encode_text, progress=progress)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if not meta["items"]:
        shutil.rmtree(tmp)
        raise LatentCacheError(f"latent cache {r}: nothing to encode (no clip pairs in split {key.split!r})")
    r.parent.mkdir(parents=True, exist_ok=True)
    if r.exists():  # an empty folder the user made
        r.rmdir()
    os.replace(tmp, r)
    return LatentCache(r, meta)


def _remove_dead_builds(root: Path) -> None:
    """Remove temporary folders of builds whose process is gone (killed mid-build)."""
    for d in root.parent.glob(f".{root.name}.building-*"):
        try:
            pid = int(d.name.rsplit("-", 1)[1])
            os.kill(pid, 0)
        except (ValueError, ProcessLookupError):
            shutil.rmtree(d, ignore_errors=True)
        except PermissionError:
            pass


def _encode(tmp: Path, key: CacheKey, sources: Iterable[CacheSource], *,
            posterior: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
            encode_text: Callable[[Sequence[str]], torch.Tensor],
            progress: Callable[[int], None] | None) -> dict[str, Any]:
    dtype = _DTYPES[key.dtype]
    items: list[dict[str, Any]] = []
    prompts: dict[str, int] = {}
    shape: list[int] = []
    for n, src in enumerate(sources):
        tensors: dict[str, torch.Tensor] = {}
        for side, clip in (("clean", src.clean), ("corrupted", src.corrupted)):
            mean, std = posterior(clip.unsqueeze(0))
            tensors[f"{side}_mean"], tensors[f"{side}_std"] = mean[0].cpu(), std[0].cpu()
        name = f"{n:06d}.safetensors"
        _write_item(tmp / "items" / name, tensors, dtype)
        idx = prompts.setdefault(src.prompt, len(prompts))
        items.append({"file": name, "pair_id": src.pair_id, "start": int(src.start), "text": idx})
        shape = list(tensors["clean_mean"].shape)
        if progress is not None:
            progress(n + 1)
    if items:
        text = encode_text(list(prompts))
        save_file({"embeddings": text.to(dtype).contiguous()}, str(tmp / "text.safetensors"))
    meta = {"key": asdict(key), "items": items, "prompts": list(prompts), "latent_shape": shape}
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    write_checksums(tmp)
    return meta
