"""Deterministic, resumable, rank-sharded sample streams for the training loop.

The loop sees training data as one endless stream of micro-batches per process. Its position is
a single number, the micro-batches this process has consumed, saved in every checkpoint; a
stream rebuilt from that number yields exactly the batches the interrupted run would have read
next, whatever the worker count.

- Map-style datasets (`PairDataset`, or a model's cached dataset) are read through
  `EpochSampler`: epoch e visits the pairs in `epoch_permutation(n, seed, e)` order, position p
  of that order goes to rank p mod world_size (the last n mod world_size are dropped so ranks stay
  in step), and each key is `(index, sample_seed(seed, e, p))`.
- `LivePairs` partitions its own sample indices (see morphgs.data.live).
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from typing import Any

import torch

from morphgs.data.seeds import epoch_permutation, sample_seed

__all__ = ["EpochSampler", "train_loader"]


class EpochSampler(torch.utils.data.Sampler):  # type: ignore[type-arg]
    """Endless (index, seed) keys over epochs for one rank, starting after `start` keys.

    Args:
        n: pairs in the dataset.
        seed: run seed.
        rank, world_size: this process and the process count.
        start: keys of this rank already consumed (resume).
        shuffle: permute each epoch (else dataset order).

    Raises:
        ValueError: fewer pairs than processes.
    """

    def __init__(self, n: int, *, seed: int, rank: int = 0, world_size: int = 1, start: int = 0,
                 shuffle: bool = True) -> None:
        if n < world_size:
            raise ValueError(f"{n} pairs cannot feed {world_size} processes (need at least one each)")
        if not 0 <= rank < world_size or start < 0:
            raise ValueError(f"bad rank {rank} of {world_size} or start {start}")
        self.n, self.seed, self.rank, self.world_size, self.start = n, int(seed), rank, world_size, int(start)
        self.shuffle = shuffle
        self.per_rank = n // world_size

    def keys(self, epoch: int) -> list[tuple[int, int]]:
        """This rank's keys of one epoch."""
        order = epoch_permutation(self.n, self.seed, epoch) if self.shuffle else range(self.n)
        return [(int(order[p]), sample_seed(self.seed, epoch, p))
                for p in range(self.rank, self.per_rank * self.world_size, self.world_size)]

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch, skip = divmod(self.start, self.per_rank)
        while True:
            yield from self.keys(epoch)[skip:]
            epoch += 1
            skip = 0

    def __len__(self) -> int:  # an epoch's worth, for progress displays
        return self.per_rank


# seconds a worker keeps serving after a SIGTERM (a cluster signals the whole process group: the
# main process finishes its step with the worker's batches, checkpoints and shuts it down)
WORKER_GRACE_S = 120


def _worker_sigterm(signum: int, frame: Any) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM (the main's terminate()) ends it
    signal.alarm(WORKER_GRACE_S)  # and it ends on its own after the grace period


def _worker_init(worker_id: int) -> None:
    """Workers leave SIGTERM and Ctrl-C to the main process, which finishes its step, checkpoints
    and shuts them down."""
    signal.signal(signal.SIGTERM, _worker_sigterm)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def train_loader(dataset: Any, *, batch_size: int, num_workers: int, seed: int, rank: int, world_size: int,
                 start_batch: int) -> torch.utils.data.DataLoader:  # type: ignore[type-arg]
    """The loop's endless DataLoader over `dataset` for one rank, positioned after `start_batch`
    micro-batches. Workers are forked; their own generator is seeded from `seed` so building the
    loader leaves torch's global random state alone. Workers ignore SIGINT and outlive a first
    SIGTERM by up to WORKER_GRACE_S (the main process stops them after its checkpoint).

    Raises:
        ValueError: fewer pairs than processes.
    """
    gen = torch.Generator().manual_seed(int(seed) ^ 0x5EED)
    common: dict[str, Any] = dict(batch_size=batch_size, num_workers=num_workers, generator=gen,
                                  persistent_workers=False, pin_memory=False,
                                  worker_init_fn=_worker_init if num_workers > 0 else None)
    if num_workers > 0:
        common["prefetch_factor"] = 2
    if isinstance(dataset, torch.utils.data.IterableDataset):
        stream = dataset.stream(start_batch=start_batch, batch_size=batch_size,  # type: ignore[attr-defined]
                                rank=rank, world_size=world_size)
        return torch.utils.data.DataLoader(stream, **common)
    sampler = EpochSampler(len(dataset), seed=seed, rank=rank, world_size=world_size,
                           start=start_batch * batch_size)
    return torch.utils.data.DataLoader(dataset, sampler=sampler, drop_last=True, **common)
