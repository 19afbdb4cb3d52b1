"""`LivePairs`: clean/corrupted pairs rendered on the fly inside DataLoader workers.

The perturbation becomes a live augmentation (the paper names it as future work; only a fast
renderer makes it possible): every sample is a fresh corruption of a scene along a fresh camera
path, so a run never sees the same pair twice.

Sample `i` of epoch `e` is a pure function of `sample_seed(run_seed, e, i)`
(`morphgs.data.seeds`): which scene, which corruption config, which camera clip (the same
trajectory rules as `morphgs curate`: recorded cameras when the scene has them, else an orbit;
one of `paths` start positions) and the perturbation seed. Scenes are loaded once per worker
(a small cache).

Partition: an epoch has `samples_per_epoch` samples; rank r of R takes indices i with
i mod R == r (the last samples_per_epoch mod R are dropped); within a rank, micro-batch b (of
`batch_size` consecutive samples) is rendered by worker b mod W. No two workers and no two ranks
render the same sample. Forking after the parent rendered is safe (morphgs's native thread pool
is per process).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from morphgs.data.seeds import rng, sample_seed

__all__ = ["LivePairs"]


@dataclass(frozen=True)
class _Position:
    start_batch: int = 0
    batch_size: int = 1
    endless: bool = False


def _rank_world(rank: int | None, world_size: int | None) -> tuple[int, int]:
    if rank is not None and world_size is not None:
        return rank, world_size
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


class LivePairs(torch.utils.data.IterableDataset):  # type: ignore[type-arg]
    """Pairs rendered live from scene files and corruption configs.

    Args:
        scenes: scene files or folders (as `morphgs curate` takes them); empty: the built-in
            synthetic scenes (`builtin_scenes` of `builtin_gaussians` Gaussians).
        configs: corruption configs, as `morphgs curate --config` (preset names, NAME@SCALE,
            blur2d[@SIGMA], JSON files); a sample picks one uniformly.
        frames: F frames per sample; size: (H, W) rendered frame size.
        samples_per_epoch: samples in one epoch over all ranks.
        seed: run seed; epoch: the epoch iterated (`set_epoch`).
        rank, world_size: this process among several (default: torch.distributed's, else 0 of 1).
        paths: camera-path start positions per scene (pair indices of `job_cameras`).
        threads: native render threads per worker (None: MORPHGS_NUM_THREADS or all CPUs).
        background, fov_y_degrees, orbit_arc_degrees: as in `morphgs curate`.
        scene_cache: scenes kept loaded per worker.

    Yields:
        dicts with `corrupted`, `clean` float32 (3, F, H, W) in [-1, 1], `scene`, `config_name`,
        `index`, `epoch`, `seed`.

    Raises:
        FileNotFoundError, MorphgsError: scenes that cannot be used (at construction) or loaded.
    """

    def __init__(
        self,
        scenes: Sequence[str | os.PathLike[str]] = (),
        *,
        configs: Sequence[str] = ("morphological",),
        frames: int = 16,
        size: Sequence[int] = (256, 256),
        samples_per_epoch: int = 1024,
        seed: int = 0,
        epoch: int = 0,
        rank: int | None = None,
        world_size: int | None = None,
        paths: int = 64,
        threads: int | None = None,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        fov_y_degrees: float = 50.0,
        orbit_arc_degrees: float = 60.0,
        builtin_scenes: int = 2,
        builtin_gaussians: int = 100_000,
        scene_cache: int = 4,
    ) -> None:
        super().__init__()
        from morphgs._core import MorphgsError
        from morphgs.curation import builtin_sources, discover, parse_config

        if frames < 1 or samples_per_epoch < 1 or paths < 1:
            raise ValueError(f"frames, samples_per_epoch and paths must be >= 1, got {frames}, "
                             f"{samples_per_epoch}, {paths}")
        h, w = (int(v) for v in size)
        if h < 1 or w < 1:
            raise ValueError(f"size must be positive (H, W), got {tuple(size)}")
        if scenes:
            sources, problems = discover(list(scenes))
            if problems:
                raise MorphgsError("; ".join(f"{src}: {msg}" for src, msg in problems))
        else:
            sources = builtin_sources(builtin_scenes, n_gaussians=builtin_gaussians)
        self.sources = sources
        self.configs = [parse_config(c) for c in configs]
        if not self.configs:
            raise ValueError("at least one corruption config is needed")
        self.frames, self.height, self.width = int(frames), h, w
        self.samples_per_epoch = int(samples_per_epoch)
        self.seed = int(seed)
        self.epoch = int(epoch)
        self.rank, self.world_size = rank, world_size
        self.paths = int(paths)
        self.threads = threads
        self.background = tuple(float(v) for v in background)
        self.fov_y_degrees, self.orbit_arc_degrees = float(fov_y_degrees), float(orbit_arc_degrees)
        self.scene_cache = max(1, int(scene_cache))
        self._position = _Position()
        self._cache: OrderedDict[str, tuple[Any, Any]] = OrderedDict()

    def set_epoch(self, epoch: int) -> None:
        """The epoch the next iteration yields (changes every sample's seed)."""
        self.epoch = int(epoch)

    def stream(self, *, start_batch: int, batch_size: int, rank: int, world_size: int) -> LivePairs:
        """An endless copy positioned after `start_batch` micro-batches of this rank (the training
        loop's stream; epochs follow one another from `self.epoch`)."""
        out = LivePairs.__new__(LivePairs)
        out.__dict__.update(self.__dict__)
        out.rank, out.world_size = rank, world_size
        out._position = replace(self._position, start_batch=int(start_batch), batch_size=int(batch_size),
                                endless=True)
        out._cache = OrderedDict()
        return out

    def __len__(self) -> int:
        """Samples this rank yields per epoch."""
        _, world = _rank_world(self.rank, self.world_size)
        return self.samples_per_epoch // world

    # ---- the pure part: one sample from its (epoch, index) ----
    def _scene(self, k: int) -> tuple[Any, Any]:
        src = self.sources[k]
        if src.id in self._cache:
            self._cache.move_to_end(src.id)
            return self._cache[src.id]
        scene = src.load()
        recorded = src.load_cameras((self.width, self.height))
        self._cache[src.id] = (scene, recorded)
        while len(self._cache) > self.scene_cache:
            self._cache.popitem(last=False)
        return scene, recorded

    def render_sample(self, epoch: int, index: int) -> dict[str, Any]:
        """Render sample `index` of `epoch` (a pure function of the run seed, epoch and index)."""
        from morphgs.curation.plan import PairJob, TrajectoryOptions, job_cameras
        from morphgs.pair import render_pair

        seed = sample_seed(self.seed, epoch, index)
        g = rng(seed)
        k = int(g.integers(len(self.sources)))
        spec = self.configs[int(g.integers(len(self.configs)))]
        path_index = int(g.integers(self.paths))
        scene, recorded = self._scene(k)
        job = PairJob(self.sources[k], spec, path_index, self.paths, seed, "train", self.frames, self.width,
                      self.height)
        opts = TrajectoryOptions(orbit_arc_degrees=self.orbit_arc_degrees, fov_y_degrees=self.fov_y_degrees)
        cams = job_cameras(job, scene, recorded, opts)
        pair = render_pair(scene, cams, config=spec, seed=seed, background=self.background)
        return {
            "corrupted": _to_tensor(pair.corrupted.rgb),
            "clean": _to_tensor(pair.clean.rgb),
            "scene": self.sources[k].id,
            "config_name": spec.label,
            "epoch": epoch,
            "index": index,
            "seed": seed,
        }

    # ---- partition over ranks and workers ----
    def _indices(self) -> Iterator[tuple[int, int]]:
        """(epoch, index) of the samples this worker renders, in order."""
        rank, world = _rank_world(self.rank, self.world_size)
        per_rank = self.samples_per_epoch // world
        if per_rank < 1:
            raise ValueError(f"samples_per_epoch={self.samples_per_epoch} cannot feed {world} processes")
        info = torch.utils.data.get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        pos = self._position
        b = pos.start_batch + worker
        stop = None if pos.endless else per_rank  # local samples of this epoch
        while True:
            for j in range(b * pos.batch_size, (b + 1) * pos.batch_size):
                if stop is not None and j >= stop:
                    return
                epoch, local = divmod(j, per_rank)
                yield self.epoch + epoch, local * world + rank
            b += workers

    def __iter__(self) -> Iterator[dict[str, Any]]:
        if self.threads is not None and torch.utils.data.get_worker_info() is not None:
            # read when this (forked) worker first renders and builds its own thread pool
            os.environ["MORPHGS_NUM_THREADS"] = str(int(self.threads))
        for epoch, index in self._indices():
            yield self.render_sample(epoch, index)


def _to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """(F, H, W, 3) float in [0, 1] -> (3, F, H, W) float32 in [-1, 1] (quantised to 8 bits, as a
    frame written to disk and read back would be, so live and stored pairs look alike)."""
    u8 = np.rint(np.clip(rgb, 0.0, 1.0) * 255.0)
    return torch.from_numpy(u8.astype(np.float32) / 127.5 - 1.0).permute(3, 0, 1, 2).contiguous()
