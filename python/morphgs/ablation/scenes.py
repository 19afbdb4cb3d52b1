"""Which scenes a study uses and how they split: pure functions of the settings and the inputs.

The seeded split orders the scene ids by sha256("morphgs/ablate-split/v1", seed, id) and puts the
first `split.test` in the test split: exact counts, independent of the input order and of how
many workers run. Explicit `train_ids`/`test_ids` lists override it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

from morphgs._core import MorphgsError
from morphgs.ablation.study import Regime, Study, StudyError

__all__ = ["SceneSet", "check_capture", "resolve_scenes", "scene_fingerprint"]


@dataclass(frozen=True)
class SceneSet:
    """The study's scenes: {id: SceneSource}, the two splits, and each scene's capture views."""

    sources: dict[str, Any]
    train: list[str]
    test: list[str]
    views: dict[str, int]


def _order(seed: int, sid: str) -> str:
    return hashlib.sha256(f"morphgs/ablate-split/v1\0{seed}\0{sid}".encode()).hexdigest()


def scene_fingerprint(source: Any) -> dict[str, Any]:
    """What a capture reads of a scene: the built-in parameters, or the scene file's and the
    cameras file's contents (sha256)."""
    if source.builtin is not None:
        return {"builtin": source.builtin}
    out: dict[str, Any] = {"id": source.id}
    for name, p in (("scene", source.path), ("cameras", source.cameras)):
        if p is None:
            continue
        out[name] = _sha256(p)
    if source.capture is not None:  # the photos the clean fit and the capture read
        from morphgs.fit import load_posed_images

        posed = load_posed_images(source.capture)
        h = hashlib.sha256()
        for p in posed.paths:
            h.update(f"{p.name}\0{_sha256(p)}\0".encode())
        out["photos"] = h.hexdigest()
        if posed.points is not None:
            out["points"] = _sha256(posed.points)
    return out


def _sha256(path: Any) -> str:
    """A file's sha256, or a folder's (a COLMAP model): its files' names and contents."""
    from pathlib import Path

    p = Path(path)
    if p.is_dir():
        h = hashlib.sha256()
        for x in sorted(x for x in p.iterdir() if x.is_file()):
            h.update(f"{x.name}\0{_sha256(x)}\0".encode())
        return h.hexdigest()
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_capture(study: Study, source: Any) -> None:
    """A capture given as photos is usable: every camera has its photo (one line naming the
    capture, the camera and the missing file otherwise)."""
    from morphgs.fit import load_posed_images

    try:
        posed = load_posed_images(source.capture)
    except (OSError, ValueError, MorphgsError) as e:
        raise StudyError(f"{study.source}: scenes.inputs: {source.id}: {e}") from None
    missing = [i for i, p in enumerate(posed.paths) if not p.is_file()]
    if missing:
        i = missing[0]
        raise StudyError(f"{study.source}: scenes.inputs: {source.id}: camera {i} of {posed.source} has no photo "
                         f"({posed.paths[i]} is missing; {len(missing)} of {len(posed)} are): add the photos or "
                         "drop their cameras")
    from PIL import Image, UnidentifiedImageError

    from morphgs.fit.data import fit_camera_to_image

    for i, (p, cam) in enumerate(zip(posed.paths, posed.cameras)):  # headers only: cheap, before any fit
        try:
            with Image.open(p) as im:
                w, h = im.size
        except (OSError, UnidentifiedImageError) as e:
            raise StudyError(f"{study.source}: scenes.inputs: {source.id}: {p}: not a readable image "
                             f"({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
        try:
            fit_camera_to_image(cam, w, h, p)
        except MorphgsError as e:
            raise StudyError(f"{study.source}: scenes.inputs: {source.id}: camera {i}: {e}") from None


def resolve_scenes(study: Study, *, check_views: bool = True) -> SceneSet:
    """The scenes, their split and capture view counts.

    Raises:
        StudyError: a scene input that cannot be read, an unknown id in an explicit split, an
            empty split, or a test scene with too few capture views for a regime (naming it).
    """
    from morphgs.curation.sources import builtin_sources, discover

    from morphgs.ablation.presets import NEEDS_INPUTS

    sc, sp = study["scenes"], study["split"]
    if study.preset in NEEDS_INPUTS and not sc["inputs"]:
        raise StudyError(f"{study.source}: scenes.inputs: the {study.preset} preset runs on real captures: list "
                         'their folders (inputs = ["captures/statue", ...]; photos with transforms.json or a '
                         "COLMAP model)")
    size = tuple(study["capture"]["size"])
    if sc["inputs"]:
        found, problems = discover(sc["inputs"], captures=True)
        if problems:
            inp, msg = problems[0]
            raise StudyError(f"{study.source}: scenes.inputs: {inp}: {msg}")
    else:
        found = builtin_sources(int(sc["builtin"]), n_gaussians=int(sc["builtin_gaussians"]))
    sources = {s.id: s for s in found}
    if sp["train_ids"] or sp["test_ids"]:
        for key in ("train_ids", "test_ids"):
            unknown = [i for i in sp[key] if i not in sources]
            if unknown:
                raise StudyError(f"{study.source}: split.{key}: unknown scene id(s) {unknown} "
                                 f"(the scenes are {sorted(sources)})")
        train, test = list(sp["train_ids"]), list(sp["test_ids"])
        both = set(train) & set(test)
        if both:
            raise StudyError(f"{study.source}: split: scene(s) {sorted(both)} are in both train_ids and test_ids")
    else:
        order = sorted(sources, key=lambda s: _order(int(sp["seed"]), s))
        test, train = sorted(order[: int(sp["test"])]), sorted(order[int(sp["test"]):])
    if not train:
        raise StudyError(f"{study.source}: split: empty training split ({len(sources)} scene(s), "
                         f"{len(test)} of them in the test split)")
    if not test:
        raise StudyError(f"{study.source}: split: empty test split")
    views = {}
    for sid in train + test:
        src = sources[sid]
        if src.capture is not None:
            check_capture(study, src)
        rec = src.load_cameras(size) if check_views and src.builtin is None else None
        views[sid] = len(rec) if rec is not None else int(study["capture"]["views"])
    for sid in test:
        for r in study.regimes:
            _check_regime(study, sid, views[sid], r)
        fr = int(study["clips"]["frames"])
        if sources[sid].capture is not None and views[sid] < fr:
            raise StudyError(f"{study.source}: test scene {sid} has {views[sid]} photos, fewer than a test clip's "
                             f"clips.frames = {fr} (its clips are runs of consecutive photos)")
    if study["conditions"]["clean"] == "photo":  # pairs at the photos: every training scene needs them
        bare = [sid for sid in train if sources[sid].capture is None]
        if bare:
            raise StudyError(f"{study.source}: conditions.clean = 'photo': training scene(s) {', '.join(bare)} are "
                             "not captures of photos (give photo folders as scenes.inputs, or clean = 'render')")
        fr = int(study["clips"]["frames"])
        few = [sid for sid in train if views[sid] < fr]
        if few:
            raise StudyError(f"{study.source}: conditions.clean = 'photo': training scene {few[0]} has {views[few[0]]} "
                             f"photos, fewer than a pair's clips.frames = {fr}")
    if any(c.kind in ("target", "calibrated") for c in study.conditions):  # they need real pairs of the train scenes
        for sid in train:
            for r in study.regimes:
                _check_regime(study, sid, views[sid], r)
    return SceneSet(sources, train, test, views)


def _check_regime(study: Study, sid: str, views: int, r: Regime) -> None:
    if views < r.min_views():
        raise StudyError(f"{study.source}: scene {sid} has {views} capture views, too few for regime {r.label} "
                         f"(it needs at least {r.min_views()} so that 2 views remain to fit from)")


def capture_size(study: Study) -> tuple[int, int]:
    w, h = study["capture"]["size"]
    return int(w), int(h)
