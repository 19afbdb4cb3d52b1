"""Before any work: the model's weight folders must exist (sandbox: model.sd15 and
model.motion_adapter; controlnet: model.wan), from the study's model config file and overrides."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from morphgs.ablation.study import Study, StudyError

__all__ = ["REQUIRED_FOLDERS", "check_model_folders", "missing_model_folders"]

REQUIRED_FOLDERS = {"tiny": (), "sandbox": ("sd15", "motion_adapter"), "controlnet": ("wan",)}


def _model_section(study: Study) -> dict[str, Any]:
    from morphgs.configfile import load_toml

    section: dict[str, Any] = {}
    if study["model"]["config"]:
        p = Path(study["model"]["config"])
        if not p.is_file():
            raise StudyError(f"{study.source}: model.config: {p}: no such model config file")
        _, d = load_toml(p)
        section.update(d.get("model", {}) if isinstance(d.get("model"), dict) else {})
    over = study["model"]["overrides"].get("model", {})
    section.update(over if isinstance(over, dict) else {})
    return section


def missing_model_folders(study: Study) -> list[str]:
    """'model.KEY: PATH (why)' for each required weights folder that is not there."""
    sec = _model_section(study)
    out = []
    for key in REQUIRED_FOLDERS.get(study["model"]["name"], ()):  # plugin models: none known
        v = sec.get(key, "")
        if not v:
            out.append(f"model.{key}: not set (a local folder of the weights)")
        elif not Path(v).exists():
            out.append(f"model.{key}: {v}: no such folder")
    return out


def check_model_folders(study: Study) -> None:
    """Raises StudyError naming the study file and every missing model folder."""
    missing = missing_model_folders(study)
    if missing:
        src = study["model"]["config"] or study.source
        raise StudyError(f"{src}: the {study['model']['name']} model's folders are missing: {'; '.join(missing)} "
                         "(set them in the model config or [model.overrides.model])")
