"""A trained refiner on a curated folder's split, as `ClipPair`s (`morphgs eval --run RUN --data DIR`).

For every pair of the split, the run's model refines the corrupted clip (`morphgs.inference`,
windows blended, Reinhard colour correction), and two `ClipPair`s come out: label "input" (the
corrupted clip against the clean one) and label "output" (the refined clip against the clean
one), so one table shows what the refiner gains. When the pair was curated with depth and
cameras, the clean render's exact geometric flow is the flow reference of both, and the
corrupted render's depth is scored as the input's depth.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from morphgs.evaluation.core import ClipPair
from morphgs.evaluation.discover import read_cameras

__all__ = ["count_pairs", "refined_pairs"]


def count_pairs(data: str | os.PathLike[str], split: str) -> int:
    """How many pairs of `data` the split holds ("test", "train" or "all")."""
    from morphgs.data import load_records

    return sum(1 for r in load_records(data) if split == "all" or r.split == split)


def refined_pairs(
    run: str | os.PathLike[str],
    data: str | os.PathLike[str],
    *,
    split: str = "test",
    checkpoint: str | os.PathLike[str] | None = None,
    device: str | None = None,
    save_refined: str | os.PathLike[str] | None = None,
    color_correct: bool = True,
) -> Iterator[ClipPair]:
    """Yield ("input", "output") ClipPairs for every pair of the split, refining as it goes.

    Args:
        run: the run folder (`morphgs train --out`).
        data: the curated folder.
        split: "test" (default), "train" or "all".
        checkpoint: a checkpoint folder (default: the run's latest).
        device: where the model runs (default: CUDA when available, else the CPU).
        save_refined: when given, each pair's refined frames are written to
            `save_refined/<pair_id>/refined/00000.png ...`.
        color_correct: refine's Reinhard transfer to the corrupted clip's colour statistics (on
            by default, as `morphgs refine`); it hands the output the input's mean colour, so
            the two `color_shift` values then agree.

    Raises:
        FileNotFoundError, DatasetError, TrainingError: as `morphgs.inference` (each names the path).
    """
    from morphgs.inference import iter_refined_pairs, load_run

    loaded = load_run(run, checkpoint=checkpoint, device=device)
    for rp in iter_refined_pairs(loaded, data, split=split, out=save_refined, color_correct=color_correct):
        rec: Any = rp.record
        cams = read_cameras(rec.cameras) if rec.cameras is not None and rec.clean_depth is not None else None
        depth_gt = Path(rec.clean_depth) if rec.clean_depth is not None else None
        depth_in = Path(rec.corrupted_depth) if rec.corrupted_depth is not None else None
        yield ClipPair(rp.pair_id, rp.corrupted, rp.clean, depth_in, depth_gt, cams, "input")
        yield ClipPair(rp.pair_id, rp.refined, rp.clean, None, depth_gt, cams, "output")
