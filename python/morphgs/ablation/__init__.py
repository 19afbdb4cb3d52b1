"""`morphgs ablate`: the paper's perturbation ablation (its Table 1) end to end, resumable.

`load_study(path, preset=...)` reads a study file over a preset; `run_study(study, out)` runs
the recipe (morphgs.ablation.recipe: the stages and their cache keys, top to bottom) and writes
STUDY/table.md, results.json/.csv and plots/. See docs/ablation.md.
"""

from __future__ import annotations

from morphgs.ablation.presets import PRESETS
from morphgs.ablation.recipe import build_plan, run_study
from morphgs.ablation.study import Study, StudyError, load_study, to_toml

__all__ = ["PRESETS", "Study", "StudyError", "build_plan", "load_study", "run_study", "to_toml"]
