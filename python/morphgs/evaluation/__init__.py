"""`morphgs eval`: compare predicted clips with their ground truth and write the tables and plots.

    from morphgs.evaluation import ClipPair, evaluate
    report = evaluate([ClipPair("scene-a", "out/a", "gt/a")], out_dir="eval")
    report.overall["pred"]["psnr"]

`evaluate` is the core the CLI and the training helpers share: it takes any iterable of
`ClipPair`s (paths or arrays), computes the chosen metrics of `morphgs.metrics` per frame, and
writes `per_frame.csv`, `summary.md` (per clip and overall), `summary.json` and `plots/`.
Importing this package never imports torch.
"""

from __future__ import annotations

from morphgs.evaluation.core import DEFAULT_METRICS, METRICS, SELECTABLE, ClipPair, EvalError, EvalReport, evaluate
from morphgs.evaluation.discover import discover_pairs, find_clips, read_cameras

__all__ = [
    "DEFAULT_METRICS",
    "METRICS",
    "SELECTABLE",
    "ClipPair",
    "EvalError",
    "EvalReport",
    "discover_pairs",
    "evaluate",
    "find_clips",
    "read_cameras",
]
