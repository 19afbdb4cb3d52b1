"""What a calibration writes (docs/calibration.md, "Outputs"): calibration.json, a config file per
(family, regime) in configs/, report.md and its plots. `morphgs calibrate` and the ablation's
calibration stage both write through `write_outputs`; the command adds timings.json apart, so
that these files are the same bytes on every run."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from morphgs.calibration.pipeline import Calibration, rank_families

__all__ = ["document", "result_name", "write_outputs"]


def result_name(family: str, regime: str) -> str:
    """The file name (no suffix) of a (family, regime) result's config file and plots: the regime
    as `morphgs.curation.sources.slug` names files (`sparse:20` -> `sparse-20`)."""
    from morphgs.curation.sources import slug

    return f"{family}-{slug(regime, fallback='regime')}"


def document(calibration: Calibration, *, scenes: Sequence[str], real: str | None, pairs_per_scene: int, seed: int,
             fit_steps: Mapping[str, int | None]) -> dict[str, Any]:
    """calibration.json's content: `calibration` with what made its real pairs and the ranking.

    Args:
        scenes: the scenes, as `SceneSource.describe` names them. real: the --real folder or None.
        pairs_per_scene, seed: the regimes' pair making (recorded as given). fit_steps: regime ->
            its sparse fits' steps (None: curate's default).
    """
    from morphgs import __version__

    results = [{**r, "config_file": f"configs/{result_name(r['family'], r['regime'])}.json"}
               for r in calibration.results]
    return {"schema": 1, "morphgs_version": __version__, "scenes": list(scenes), "regimes": list(calibration.regimes),
            "families": list(calibration.families), "real": real, "pairs_per_scene": pairs_per_scene, "seed": seed,
            "fit_steps": dict(fit_steps), "search_mix": calibration.search_mix,
            "objective": calibration.objective, "frames": list(calibration.frames),
            "resolution": list(calibration.resolution), "results": results, "ranking": rank_families(results)}


def write_outputs(out: str | Path, doc: Mapping[str, Any], plot_data: Sequence[dict[str, Any]], *,
                  plots: bool = True) -> None:
    """Write `doc` (from `document`) into `out`: its configs (each result's `config_file`),
    report.md (and plots/*.png from `plot_data`, one per result, when `plots`) and
    calibration.json."""
    from morphgs.calibration.report import write_report

    out_dir = Path(out)
    (out_dir / "configs").mkdir(parents=True, exist_ok=True)
    for r in doc["results"]:
        (out_dir / r["config_file"]).write_text(json.dumps(r["config"], indent=1) + "\n", encoding="utf-8")
    write_report(out_dir, dict(doc), plot_data, plots=plots)
    (out_dir / "calibration.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
