"""The training `PairDataset` as cached latents: which windows are encoded, and the torch Dataset
over the cache that `forward` reads.

A latent cache holds fixed windows. For each pair, the dataset's own geometry is used (its
optional resize, then its crop, centred, exactly as `PairDataset` does in evaluation) and every
window of ``frames`` consecutive frames starting at ``0, stride, 2*stride, ...`` is encoded, plus
the centre window (the one evaluation reads). Random crops and flips do not survive latent
caching (the latent of a flipped clip is not the flipped latent), so training varies the
temporal window (drawn from the sample's seed) and the VAE noise (drawn each step).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from typing import Any

import torch

from morphgs import media
from morphgs.curation import manifest
from morphgs.diffusion.latent_cache import CacheSource, LatentCache, fingerprint

__all__ = ["LatentPairs", "cache_windows", "dataset_fingerprint", "window_sources"]


def cache_windows(dataset: Any, *, stride: int) -> list[list[Any]]:
    """Per pair of a `PairDataset`, the windows (`morphgs.data.Window`) a cache encodes."""
    out = []
    for i, rec in enumerate(dataset.records):
        centre = dataset.window(i, None)
        n = media.clip_info(rec.clean)[0]
        starts = sorted(set(range(0, n - dataset.frames + 1, stride)) | {centre.start})
        out.append([dataclasses.replace(centre, start=s) for s in starts])
    return out


def dataset_fingerprint(dataset: Any) -> str:
    """A hash of the manifest records of the dataset's pairs and its geometry (re-curating a pair,
    or changing the frame count, crop or resize, changes it)."""
    records = manifest.load(dataset.root)
    ids = [r.pair_id for r in dataset.records]
    return fingerprint({"records": [records.get(i, i) for i in ids], "frames": dataset.frames,
                        "size": dataset.size, "resize": dataset.resize})


def window_sources(dataset: Any, windows: list[list[Any]], *, prompt: str,
                   captions: Mapping[str, str] | None = None) -> Iterator[CacheSource]:
    """The clips of every cached window, in a fixed order, as (3, F, H, W) tensors in [-1, 1].

    Raises:
        FileNotFoundError, morphgs.media.MediaError: unreadable frames (the file is named).
    """
    from morphgs.data.pairs import frames_to_tensor

    for rec, wins in zip(dataset.records, windows):
        text = (captions or {}).get(rec.pair_id, prompt)
        for win in wins:
            clips = [frames_to_tensor(media.read_clip(p, start=win.start, count=win.frames), win)
                     for p in (rec.clean, rec.corrupted)]
            yield CacheSource(pair_id=rec.pair_id, start=win.start, clean=clips[0], corrupted=clips[1], prompt=text)


class LatentPairs(torch.utils.data.Dataset):  # type: ignore[type-arg]
    """The cached windows of a `PairDataset`, with its keys and length.

    ``ds[(i, seed)]`` is one of pair i's cached windows, chosen from ``seed`` (what the training
    loop's sampler passes); ``ds[i]`` draws it from torch's generator in training and takes the
    centre window in evaluation. An item holds ``clean_mean``, ``clean_std``,
    ``corrupted_mean``, ``corrupted_std`` (C, F', H', W') and ``text`` (L, D), float32, plus
    ``pair_id`` and ``start``. Sampling from the posteriors happens in the model's `forward`.
    """

    def __init__(self, cache: LatentCache, pair_ids: list[str], *, train: bool, centres: list[int]) -> None:
        self.cache = cache
        self.train = train
        by_pair: dict[str, list[int]] = {}
        for j, item in enumerate(cache.items):
            by_pair.setdefault(item["pair_id"], []).append(j)
        self.items = [by_pair[p] for p in pair_ids]
        self.centre = [next(j for j in js if cache.items[j]["start"] == c) for js, c in zip(self.items, centres)]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        from morphgs.data.seeds import rng

        if isinstance(key, tuple):
            i, seed = int(key[0]), int(key[1])
            js = self.items[i]
            j = js[int(rng(seed).integers(0, len(js)))] if self.train else self.centre[i]
        else:
            i = int(key)
            js = self.items[i]
            j = js[int(torch.randint(0, len(js), (1,)).item())] if self.train else self.centre[i]
        return self.cache.load(j)
