"""Stage 5, refine: every test clip of a test set through one model, or through a control row.

- a trained run: `inference.refine_clip` (windows of the run's length, cross-faded; Reinhard
  colour correction against the input, as `morphgs refine` does);
- `input`: the corrupted clip as it is (no refiner);
- `identity`: the same refine path with a model that returns its input (windows, blending,
  colour correction), so the pipeline's own effect is visible;
- `oracle`: the clean clip (the ceiling).

Output: `clips/<j>/frames/*.png` (uint8, what the metrics read).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "make"]

VERSION = 1
IGNORE = ("threads",)
RESUMABLE = False


def _identity_model(window: int) -> Any:
    import torch

    class IdentityRefiner(torch.nn.Module):
        """A refiner that returns its input (the `identity` control row)."""

        size_multiple = 1

        def __init__(self) -> None:
            super().__init__()
            self.window = window
            self._device_anchor = torch.nn.Parameter(torch.zeros(()), requires_grad=False)

        def refine(self, x: Any, reference: Any = None, generator: Any = None) -> Any:
            return x

    return IdentityRefiner().eval()



def make(work: Path, *, testset_dir: str, row: str, run_dir: str | None, window: int, threads: int) -> None:
    from morphgs import media
    from morphgs.ablation.stages.common import read_testset, torch_threads
    from morphgs.inference import load_run, refine_clip

    torch_threads(threads)
    ts = Path(testset_dir)
    meta = read_testset(ts)
    model: Any = None
    if run_dir is not None:
        model = load_run(run_dir, device="cpu").model
    elif row == "identity":
        model = _identity_model(window)
    for j in meta["clips"]:
        bad = media.read_clip(ts / "clips" / j / "corrupted")
        if row == "input":
            out: np.ndarray = bad
        elif row == "oracle":
            out = media.read_clip(ts / "clips" / j / "clean")
        else:
            out = refine_clip(model, bad, device="cpu")
        media.write_frames(work / "clips" / j / "frames", out)
    (work / "refine.json").write_text(json.dumps({"row": row, "clips": meta["clips"]}, indent=1) + "\n",
                                      encoding="utf-8")
