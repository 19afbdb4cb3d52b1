"""A study's rows, parsed once: `Condition.parse(name)` gives the kind of a training set (a curate
config, a regime's target, a calibrated family) or of a control row, with its regime and family.

    morphological, naive, blur2d, x/strong.json     kind "config" (curate's --config strings)
    target-S20                                      kind "target", regime S20
    calibrated:morphological-S20                    kind "calibrated", family morphological, regime S20
    realistic:sparse-like-S20                       kind "calibrated", objective "realism" (its op mix
                                                    searched for realism, `calibrate --objective realism`)
    realistic:fams/shatter-led.json-S20             the same with a family file ({"family", "ops"}: the
                                                    ops and their proportions, `calibrate --family`),
                                                    labelled by its stem: realistic:shatter-led-S20
    input, identity, oracle                         kind "control" (not trained; do not compete)

Names are what results.json, results.csv and table.md carry; everything else (the folder slug,
the label the table shows, which regime a row belongs to) is derived here and nowhere else.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["CALIBRATED", "CONTROLS", "REALISTIC", "TARGET", "Condition"]

#: The prefix of a calibrated condition in `conditions.train`: `calibrated:FAMILY` is, per regime
#: S_K, FAMILY's strength distribution calibrated against that regime's target training set
#: (`morphgs calibrate --real`), curated on the training scenes (condition `calibrated:FAMILY-S_K`).
CALIBRATED = "calibrated:"
#: The prefix of a realism-calibrated condition: as `calibrated:`, with the family's op mix searched
#: for the pairs a classifier can least tell from the target's (`morphgs calibrate --objective realism`).
REALISTIC = "realistic:"
#: A regime's label at the end of a calibrated condition's name (`-S20`, `-N6`).
_REGIME = re.compile(r"^(?P<family>.+)-(?P<regime>[SN][0-9]+)$")
#: The prefix of a regime's target: its real sparse-view pairs (`target-S20`).
TARGET = "target-"
#: The rows every regime shows besides the trained ones: the corrupted input as it is, the
#: refine path with a model that returns its input, and the clean clip (the ceiling).
CONTROLS = ("input", "identity", "oracle")


@dataclass(frozen=True)
class Condition:
    """One row of the study (see the module docstring for the kinds)."""

    name: str
    kind: str
    regime: str | None = None
    family: str | None = None
    objective: str = "psnr"

    @classmethod
    def parse(cls, name: str) -> Condition:
        """The condition of a name as the study writes it (no validation of a config string:
        `study.load_study` checks those with curate's parser)."""
        if name in CONTROLS:
            return cls(name, "control")
        if name.startswith(TARGET):
            return cls(name, "target", regime=name[len(TARGET):])
        for prefix, objective in ((CALIBRATED, "psnr"), (REALISTIC, "realism")):
            if name.startswith(prefix):
                body = name[len(prefix):]
                m = _REGIME.match(body)  # family names may hold '-' (sparse-like); regime labels do not
                family, regime = (m["family"], m["regime"]) if m else (body, None)
                return cls(name, "calibrated", regime=regime, family=family, objective=objective)
        return cls(name, "config")

    @classmethod
    def target(cls, regime: str) -> Condition:
        return cls(f"{TARGET}{regime}", "target", regime=regime)

    @classmethod
    def calibrated(cls, family: str, regime: str, objective: str = "psnr") -> Condition:
        prefix = REALISTIC if objective == "realism" else CALIBRATED
        return cls(f"{prefix}{family}-{regime}", "calibrated", regime=regime, family=family, objective=objective)

    @property
    def trained(self) -> bool:
        """A refiner is trained on it (every kind but the control rows)."""
        return self.kind != "control"

    @property
    def family_file(self) -> bool:
        """A calibrated condition whose family is a JSON family file (not a built-in family name)."""
        return self.family is not None and self.family.lower().endswith(".json")

    @property
    def label(self) -> str:
        """As the table shows it: a JSON config by its file stem (as curate labels it), a calibrated
        condition of a family file by the file's stem."""
        if self.kind == "config" and self.name.lower().endswith(".json"):
            return Path(self.name).stem
        if self.family_file:
            prefix = REALISTIC if self.objective == "realism" else CALIBRATED
            return f"{prefix}{Path(str(self.family)).stem}" + (f"-{self.regime}" if self.regime else "")
        return self.name

    @property
    def slug(self) -> str:
        """As a folder name (a JSON path's slashes and the like become '_')."""
        return re.sub(r"[^A-Za-z0-9.@+_-]+", "_", self.label).strip("._") or "condition"

    def in_regime(self, regime: str) -> bool:
        """Whether the row is shown in `regime`'s part of the table (rows without a regime are in all)."""
        return self.regime is None or self.regime == regime
