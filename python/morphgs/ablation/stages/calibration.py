"""Stage 2b, calibration: a calibrated condition's strength distribution (`calibrated:FAMILY`).

Per regime S_K, `morphgs calibrate --real` of FAMILY against that regime's target training set:
the real sparse-view pairs of the training scenes (the very pairs target-S_K trains on), with the
training scenes' capture folders as the clean scenes. The result is the strength-distribution
config (`config.json`, `{"kind": "strength", "family", "ops", "quantiles"}`) that the calibrated
training set is curated with, plus calibrate's own outputs in `calib/` (calibration.json,
report.md with the goodness of fit on the held-out half of the training scenes) and a short
`summary.json` that the report prints.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["CONFIG", "IGNORE", "RESUMABLE", "SUMMARY", "VERSION", "make", "summary"]

VERSION = 5  # 2: the CNN two-sample test (realism) in calibration.json and summary.json; objective
# 3: the realism search's first trial is the family as given; shatter's bytes (its Rust kernel)
# 4: shatter's bytes (fragments reaching another view from outside its image dropped)
# 5: the realism search's objective breaks AUC ties by the classifier's separation d'
IGNORE: tuple[str, ...] = ()
RESUMABLE = False
CONFIG = "config.json"
SUMMARY = "summary.json"


def summary(result: dict[str, Any]) -> dict[str, Any]:
    """The few figures of one calibrate result the ablation report shows."""
    s = result["search"]
    q = dict(zip(s["quantiles"]["p"], s["quantiles"]["strength"]))
    g = result.get("goodness", {})
    realism = result.get("realism") or {}
    clf, floor = realism.get("classifier") or {}, realism.get("floor") or {}
    return {"auc": clf.get("auc"), "auc_ci": clf.get("ci"), "separation": clf.get("separation"),
            "floor_auc": floor.get("auc"),
            "indistinguishable": realism.get("indistinguishable"),"family": result["family"], "real_median_psnr": s["target_median_psnr"],
            "reachable": s["reachable"], "monotone": s["monotone"], "median_strength": s["median_strength"],
            "median_psnr_reached": s["median_psnr_reached"], "most_severe_psnr": s["most_severe_psnr"],
            "unreachable_pairs": s["unreachable_frames"], "strength_p05": q.get(0.05), "strength_p50": q.get(0.5),
            "strength_p95": q.get(0.95), "matched": g.get("matched"), "furthest": g.get("furthest"),
            "calibration_scenes": result.get("calibration_scenes")}


def make(work: Path, *, scene_dirs: list[str], real_dir: str, family: str, grid: Sequence[float],
         objective: str) -> None:
    """Calibrate `family` against the curated real pairs in `real_dir` into `work/calib` (with
    `objective` "realism", its op mix searched first: `calibrate --objective realism`, its state in
    `work/calib/realism/`); write `work/config.json` (the strength distribution) and
    `work/summary.json`."""
    from morphgs.ablation.study import StudyError
    from morphgs.calibration.outputs import document, write_outputs
    from morphgs.calibration.pairs import CalibrationError, by_regime, read_real_pairs
    from morphgs.calibration.pipeline import calibrate_pairs, parse_family
    from morphgs.calibration.run import find_scenes, load_scenes

    try:
        sources = find_scenes(scene_dirs)
        groups = by_regime(read_real_pairs(real_dir))
        calibration = calibrate_pairs(groups, load_scenes(sources, groups), [parse_family(family)], grid=list(grid),
                                      objective=objective, state_dir=work / "calib" / "realism")
    except CalibrationError as e:
        raise StudyError(f"calibration of {family} against {real_dir}: {e}") from None
    # pairs_per_scene and seed: `calibrate`'s defaults, which this stage's calibration.json has
    # always recorded (they describe the pairs of a --regime; these pairs are read, not made)
    doc = document(calibration, scenes=[s.describe() for s in sources], real=real_dir, pairs_per_scene=2, seed=0,
                   fit_steps={})
    write_outputs(work / "calib", doc, calibration.plots, plots=True)
    (result,) = doc["results"]
    (work / CONFIG).write_text(json.dumps(result["config"], indent=1, sort_keys=True) + "\n", encoding="utf-8")
    (work / SUMMARY).write_text(json.dumps(summary(result), indent=1, sort_keys=True) + "\n", encoding="utf-8")
