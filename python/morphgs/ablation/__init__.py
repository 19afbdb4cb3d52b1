"""`morphgs ablate`: the paper's perturbation ablation (its Table 1) end to end, resumable.

`load_study(path, preset=...)` reads a study file over a preset; `build_plan(study, out)` lists
its jobs (morphgs.ablation.recipe: the stages and what each reads, top to bottom); `run_study(study,
out)` runs them (morphgs.ablation.executor) and writes STUDY/table.md, results.json/.csv and
plots/. See docs/ablation.md.

    study.py, presets.py, conditions.py, scenes.py   the settings, the rows, the scenes and their split
    recipe.py, jobs.py                               the plan: jobs, their arguments and derived keys
    executor.py, cache.py                            running the jobs; the stage cache
    stages/                                          one module per stage (make, VERSION, IGNORE)
    table.py, plots.py, stats.py                     the report's table, plots and statistics
"""

from __future__ import annotations

from morphgs.ablation.executor import run_study
from morphgs.ablation.presets import PRESETS
from morphgs.ablation.recipe import build_plan
from morphgs.ablation.study import Study, StudyError, load_study, to_toml

__all__ = ["PRESETS", "Study", "StudyError", "build_plan", "load_study", "run_study", "to_toml"]
