"""Training data for refiners (torch): clips of curated pairs from disk (`PairDataset`) and pairs
rendered live in DataLoader workers (`LivePairs`), with the deterministic, resumable sampling the
training loop uses. Needs `pip install 'morphgs[train]'`; see docs/training.md.
"""

from __future__ import annotations

from morphgs.data.live import LivePairs
from morphgs.data.pairs import DatasetError, PairDataset, PairRecord, load_records
from morphgs.data.sampling import EpochSampler, train_loader
from morphgs.data.seeds import sample_seed
from morphgs.data.window import Window

__all__ = [
    "DatasetError",
    "EpochSampler",
    "LivePairs",
    "PairDataset",
    "PairRecord",
    "Window",
    "load_records",
    "sample_seed",
    "train_loader",
]
