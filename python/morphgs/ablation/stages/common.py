"""What several stages share: torch's thread count for a job, and reading a test set's index."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["read_testset", "torch_threads"]


def torch_threads(threads: int) -> None:
    """Fix torch's intra-op threads for this job (0 leaves torch's default). The bytes do not
    depend on it: the stages that take `threads` list it in their IGNORE."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))


def read_testset(testset_dir: str | Path) -> dict[str, Any]:
    """testset.json of a finished test-set output: scene, regime, train_views, capture_views,
    clips (their folder names under clips/) and bbox_diagonal."""
    return dict(json.loads((Path(testset_dir) / "testset.json").read_text(encoding="utf-8")))
