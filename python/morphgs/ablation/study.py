"""The study file: a TOML over a preset, checked key by key, pinned in full.

    [study]      seeds                  [conditions]  train, targets, pairs_per_scene, blur_sigma
    [scenes]     inputs, builtin, ...   [regimes]     every, n
    [split]      seed, test, *_ids      [clips]       frames, per_scene, heldout
    [capture]    views, size            [model] [training] [sparse] [clean] [refit] [metrics]

`load_study(path, preset=...)` gives a `Study`: the full settings tree (`settings`, every key
present, as `--print-config` shows it) and what is derived from it (the conditions as curate
`ConfigSpec`s, the regimes). Unknown keys, wrong types and impossible values raise
`StudyError` naming the file, the key and the problem.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsError
from morphgs.ablation import presets
from morphgs.ablation.conditions import Condition

__all__ = ["Regime", "Study", "StudyError", "flatten", "load_study", "to_toml"]


class StudyError(MorphgsError):
    """A study file or study folder that cannot be used (names the file, key and problem)."""


@dataclass(frozen=True)
class Regime:
    """A sparse-view regime of the test side: every K-th capture view (S_K) or N views."""

    label: str
    params: dict[str, int]

    def min_views(self) -> int:
        """Capture views a scene needs so that the regime keeps at least 2 training views."""
        return self.params["every"] + 1 if "every" in self.params else self.params["n"]


@dataclass(frozen=True)
class Study:
    """A checked study: `settings` (the full tree) and `source` (where it came from)."""

    settings: dict[str, Any]
    source: str
    preset: str

    def __getitem__(self, section: str) -> dict[str, Any]:
        return self.settings[section]

    @property
    def regimes(self) -> list[Regime]:
        r = self.settings["regimes"]
        return ([Regime(f"S{k}", {"every": int(k)}) for k in r["every"]]
                + [Regime(f"N{n}", {"n": int(n)}) for n in r["n"]])

    @property
    def conditions(self) -> list[Condition]:
        """The trained rows: the training sets as written (a `calibrated:FAMILY` one per regime,
        `calibrated:FAMILY-S20`), then one target per regime."""
        out = []
        for c in self.settings["conditions"]["train"]:
            cond = Condition.parse(c)
            if cond.kind == "calibrated":
                out += [Condition.calibrated(str(cond.family), r.label, cond.objective) for r in self.regimes]
            else:
                out.append(cond)
        if self.settings["conditions"]["targets"]:
            out += [Condition.target(r.label) for r in self.regimes]
        return out

    @property
    def seeds(self) -> list[int]:
        return [int(s) for s in self.settings["study"]["seeds"]]


def _where(source: str, key: str) -> str:
    return f"{source}: {key}"


def _check_types(default: Any, value: Any, key: str, source: str) -> None:
    if isinstance(default, dict):
        if not isinstance(value, dict):
            raise StudyError(f"{_where(source, key)} must be a table")
        if key.endswith("overrides"):
            return
        for k in value:
            if k not in default:
                known = ", ".join(sorted(default))
                raise StudyError(f"{_where(source, f'{key}.{k}' if key else k)}: unknown key (known: {known})")
            _check_types(default[k], value[k], f"{key}.{k}" if key else k, source)
        return
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif isinstance(default, str):
        ok = isinstance(value, str)
    elif isinstance(default, list):
        ok = isinstance(value, list)
    else:
        ok = True
    if not ok:
        raise StudyError(f"{_where(source, key)} must be {type(default).__name__}, got {value!r}")


def _ints(lst: Any, key: str, source: str, lo: int) -> list[int]:
    if not all(isinstance(v, int) and not isinstance(v, bool) and v >= lo for v in lst):
        raise StudyError(f"{_where(source, key)} must be a list of integers >= {lo}, got {lst!r}")
    return [int(v) for v in lst]


def _validate(s: dict[str, Any], source: str) -> None:
    from morphgs.curation.plan import parse_config

    seeds = _ints(s["study"]["seeds"], "study.seeds", source, 0)
    if not seeds or len(set(seeds)) != len(seeds):
        raise StudyError(f"{_where(source, 'study.seeds')} must be distinct integers, at least one")
    up = s["capture"]["up"]
    if up not in ("file", "scene"):
        from morphgs.trajectory import parse_up

        try:
            parse_up(up)
        except ValueError as e:
            raise StudyError(f"{_where(source, 'capture.up')}: {e} (or file, scene)") from None
    names = s["conditions"]["train"]
    if not names and not s["conditions"]["targets"]:
        raise StudyError(f"{_where(source, 'conditions.train')}: no conditions (and targets = false)")
    for c in names:
        if not isinstance(c, str):
            raise StudyError(f"{_where(source, 'conditions.train')}: {c!r} is not a curate config string")
        cond = Condition.parse(c)
        if cond.kind in ("target", "control"):
            raise StudyError(f"{_where(source, 'conditions.train')}: {c!r} is not a training set "
                             "(targets come from conditions.targets; input, identity and oracle are always shown)")
        if cond.kind == "calibrated":
            _check_family(cond, _where(source, "conditions.train"))
            continue
        try:
            parse_config(c, blur_sigma=float(s["conditions"]["blur_sigma"]))
        except (ValueError, MorphgsError) as e:
            raise StudyError(f"{_where(source, 'conditions.train')}: unknown condition {c!r} ({e})") from None
    if len(set(names)) != len(names):
        raise StudyError(f"{_where(source, 'conditions.train')}: a condition is listed twice: {names}")
    slugs: dict[str, str] = {}
    for c in names:  # JSON files are labelled (and foldered) by their stem: two of one stem would collide
        other = slugs.setdefault(Condition.parse(c).slug, c)
        if other != c:
            raise StudyError(f"{_where(source, 'conditions.train')}: {other!r} and {c!r} have the same label "
                             f"{Condition.parse(c).label!r} (JSON files are labelled by their name): rename one file")
    if s["conditions"]["clean"] not in ("render", "photo"):
        raise StudyError(f"{_where(source, 'conditions.clean')} must be 'render' or 'photo', got "
                         f"{s['conditions']['clean']!r}")
    if s["conditions"]["pairs_per_scene"] < 1:
        raise StudyError(f"{_where(source, 'conditions.pairs_per_scene')} must be >= 1")
    every = _ints(s["regimes"]["every"], "regimes.every", source, 2)
    n = _ints(s["regimes"]["n"], "regimes.n", source, 2)
    if not every and not n:
        raise StudyError(f"{_where(source, 'regimes')}: no regime (give regimes.every and/or regimes.n)")
    fr = s["clips"]["frames"]
    if fr < 4:
        raise StudyError(f"{_where(source, 'clips.frames')} must be >= 4, got {fr}")
    held = _ints(s["clips"]["heldout"], "clips.heldout", source, 0)
    if not held or any(h >= fr for h in held) or len(set(held)) != len(held) or fr - len(held) < 2:
        raise StudyError(f"{_where(source, 'clips.heldout')} must be distinct frame indices in [0, {fr}) "
                         f"leaving >= 2 training frames, got {held}")
    if s["clips"]["per_scene"] < 1:
        raise StudyError(f"{_where(source, 'clips.per_scene')} must be >= 1")
    size = _ints(s["capture"]["size"], "capture.size", source, 8)
    if len(size) != 2:
        raise StudyError(f"{_where(source, 'capture.size')} must be [W, H]")
    crop = _ints(s["training"]["crop"], "training.crop", source, 4)
    if len(crop) != 2 or crop[0] > size[1] or crop[1] > size[0]:
        raise StudyError(f"{_where(source, 'training.crop')} must be [H, W] within capture.size [W, H] = {size}")
    if s["model"]["name"] == "tiny":  # its crops must be multiples of its pixel-unshuffle x levels
        from morphgs.models.tiny import TinyConfig

        try:
            m = TinyConfig(**dict(s["model"]["overrides"].get("model", {}))).size_multiple
        except (TypeError, ValueError):
            m = 1  # a bad model override is named where the model is built
        if crop[0] % m or crop[1] % m:
            raise StudyError(f"{_where(source, 'training.crop')} must be multiples of {m} for the tiny refiner, got "
                             f"{crop} (e.g. [{max(m, crop[0] // m * m)}, {max(m, crop[1] // m * m)}])")
    if s["training"]["window"] < 1 or s["training"]["window"] > fr:
        raise StudyError(f"{_where(source, 'training.window')} must be in [1, clips.frames = {fr}]")
    for sec in ("training", "sparse", "clean", "refit"):
        if s[sec]["steps"] < 1:
            raise StudyError(f"{_where(source, sec + '.steps')} must be >= 1")
    for sec in ("sparse", "clean", "refit"):  # the fits' initial points and MCMC cap
        for key in ("random_points", "cap_max"):
            if s[sec][key] < 1:
                raise StudyError(f"{_where(source, f'{sec}.{key}')} must be >= 1, got {s[sec][key]}")
    if s["training"]["probe_every"] < 1:
        raise StudyError(f"{_where(source, 'training.probe_every')} must be >= 1")
    from morphgs.models.registry import list_models

    if s["model"]["name"] not in list_models():
        raise StudyError(f"{_where(source, 'model.name')}: unknown model {s['model']['name']!r} "
                         f"(the registry's models: {', '.join(list_models())})")
    if s["metrics"]["lpips"] not in ("auto", "off"):
        raise StudyError(f"{_where(source, 'metrics.lpips')} must be 'auto' or 'off'")
    if not s["metrics"]["fscore"] or not all(isinstance(t, (int, float)) and 0 < t < 1 for t in s["metrics"]["fscore"]):
        raise StudyError(f"{_where(source, 'metrics.fscore')} must be shares of the bbox diagonal in (0, 1)")
    sp = s["split"]
    if bool(sp["train_ids"]) != bool(sp["test_ids"]) and (sp["train_ids"] or sp["test_ids"]):
        empty = "split.train_ids" if not sp["train_ids"] else "split.test_ids"
        raise StudyError(f"{_where(source, empty)}: empty split (give both train_ids and test_ids, or neither)")
    if not sp["test_ids"] and sp["test"] < 1:
        raise StudyError(f"{_where(source, 'split.test')}: empty split (the test split needs >= 1 scene)")


def load_study(path: str | os.PathLike[str] | None, *, preset: str | None = None, up: str | None = None) -> Study:
    """The study of a TOML file over a preset (default: the file's `preset = "..."`, else toy).

    Raises:
        FileNotFoundError: no such study file. StudyError: unknown keys, bad values, unknown
            conditions, an empty split (each naming the file and key).
    """
    from morphgs.configfile import ConfigError, load_toml

    data: dict[str, Any] = {}
    source = "<preset>"
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such study file")
        try:
            _, data = load_toml(p)
        except ConfigError as e:
            raise StudyError(str(e)) from None
        source = str(p)
    name = preset or data.pop("preset", None) or "toy"
    data.pop("preset", None)
    if name not in presets.PRESETS:
        raise StudyError(f"{source}: unknown preset {name!r} ({', '.join(presets.PRESETS)})")
    base = presets.preset(name)
    _check_types(base, data, "", source)
    settings = presets.merge(base, data)
    if up is not None:  # --up on the command line
        settings["capture"]["up"] = up
    # a relative scene path or model config is relative to the study file
    if path is not None:
        root = Path(path).resolve().parent
        settings["scenes"]["inputs"] = [str(root / x) if not Path(x).is_absolute() else x
                                        for x in settings["scenes"]["inputs"]]
        settings["conditions"]["train"] = [_relative_to(root, c) for c in settings["conditions"]["train"]]
        if settings["model"]["config"] and not Path(settings["model"]["config"]).is_absolute():
            settings["model"]["config"] = str(root / settings["model"]["config"])
    _validate(settings, source)
    return Study(settings, source, name)


def _check_family(cond: Condition, where: str) -> None:
    """A `calibrated:` / `realistic:` condition's family: a built-in family name or a readable
    JSON family file; `realistic:` searches an op mix, so its family needs two ops or more."""
    from morphgs.calibration.pairs import CalibrationError
    from morphgs.calibration.pipeline import parse_family
    from morphgs.strength import FAMILIES

    c = cond.name
    if cond.regime is not None or not (cond.family_file or cond.family in FAMILIES):
        raise StudyError(f"{where}: unknown condition {c!r} (calibrated:FAMILY and realistic:FAMILY take one of "
                         f"the families {', '.join(FAMILIES)} or a JSON family file {{\"family\", \"ops\"}})")
    family = str(cond.family)
    if cond.family_file and not Path(family).is_file():
        raise StudyError(f"{where}: {c!r}: no such family file (a path relative to the study file, or an absolute one)")
    try:
        _, base = parse_family(family)
    except CalibrationError as e:
        raise StudyError(f"{where}: {c!r}: {str(e).removeprefix(f'--family {family}: ')}") from None
    ops = getattr(base, "base", {})
    if cond.objective == "realism" and len(ops) < 2:
        raise StudyError(f"{where}: {c!r}: realistic: searches the mix of a family's ops and {family} has "
                         f"{len(ops)} ({', '.join(ops)}); use calibrated:{family}, or a family of two ops or more")


def _relative_to(root: Path, name: Any) -> Any:
    """A training condition with a JSON file (a curate config, or the family of `calibrated:` /
    `realistic:`) given relative to the study file, as a path from `root` (when that file exists)."""
    if not isinstance(name, str) or not name.lower().endswith(".json"):
        return name
    cond = Condition.parse(name)
    rel = str(cond.family) if cond.family_file else name
    prefix = name[:len(name) - len(rel)]
    return prefix + str(root / rel) if not Path(rel).is_absolute() and (root / rel).is_file() else name


def flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"a.b": value} for every leaf (model.overrides as one JSON leaf)."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and k != "overrides":
            out.update(flatten(v, key + "."))
        else:
            out[key] = json.dumps(v, sort_keys=True)
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(study: Study) -> str:
    """Every setting, pinned, as a study file that reproduces the study."""
    lines = [f"# morphgs ablate: every setting of this study, pinned (from {study.source})",
             f'preset = "{study.preset}"']
    for section, values in study.settings.items():
        lines.append(f"\n[{section}]")
        for k, v in values.items():
            lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"
