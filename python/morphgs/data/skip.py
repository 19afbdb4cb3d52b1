"""`SkipBadPairs`: a map-style dataset that, instead of failing on a pair it cannot read, serves
the next readable pair and says which one it skipped (`data.skip_bad = true` in a run config).

The substitute is a pure function of the key: pair i unreadable -> pair i+1 (then i+2, ...)
with the same window seed, so a resumed or multi-worker run reads exactly the same samples.
Every sample gets a `bad` entry: "" or the skipped pairs, one "PAIR_ID<TAB>message" per line;
the training loop logs them in the run folder (`bad_pairs.jsonl`), counts them and stops when
more than `data.max_bad_share` of the pairs are bad.
"""

from __future__ import annotations

from typing import Any

import torch

from morphgs._core import MorphgsError
from morphgs.data.pairs import DatasetError
from morphgs.reliability import one_line

__all__ = ["SkipBadPairs", "bad_entries"]


class SkipBadPairs(torch.utils.data.Dataset):  # type: ignore[type-arg]
    """Wrap a `PairDataset` (anything with `records` and `__getitem__(int | (int, seed))`)."""

    def __init__(self, dataset: Any) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getattr__(self, name: str) -> Any:  # records, root, frames, ... of the wrapped dataset
        if name == "dataset":
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        index, seed = (int(key[0]), int(key[1])) if isinstance(key, tuple) else (int(key), None)
        n = len(self.dataset)
        bad: list[str] = []
        for k in range(n):
            i = (index + k) % n
            try:
                sample = self.dataset[(i, seed) if seed is not None else i]
            except (MorphgsError, OSError, ValueError) as e:
                pid = self.dataset.records[i].pair_id
                bad.append(f"{pid}\t{one_line(e)}")
                continue
            sample["bad"] = "\n".join(bad)
            return dict(sample)
        where = getattr(self.dataset, "root", "the dataset")
        raise DatasetError(f"{where}: no pair of the split can be read (first: {bad[0].replace(chr(9), ': ')})")


def bad_entries(batch_bad: Any) -> list[tuple[str, str]]:
    """(pair_id, message) of a batch's `bad` entries (a list of strings after collation)."""
    out = []
    for text in batch_bad if isinstance(batch_bad, (list, tuple)) else [batch_bad]:
        for line in str(text).splitlines():
            pid, _, msg = line.partition("\t")
            if pid:
                out.append((pid, msg))
    return out
