"""The ablation recipe, top to bottom (docs/ablation.md): which stage outputs a study needs and what
each reads. It only describes; morphgs.ablation.executor runs the jobs.

Every stage output lives under STUDY/<stage>/<name>-<key>/. Its key derives from the arguments of
the stage's `make()` (morphgs.ablation.jobs): an upstream output counts by its key, a file by its
sha256, and the stage's VERSION is in it. So a setting reaches a key exactly when it reaches a
stage, and a rerun remakes what a change touches, nothing else:

    cleanfits/<scene>                 a capture given as photos (its files' hashes), size, [clean]
    captures/<scene>                  the scene (its files' hashes or built-in parameters), views, size, up,
                                      the clean fit
    pairfits/<condition>-<scene>      a fit-based condition's (target, underfit, cross) fit of one train scene:
                                      its capture, the condition's curate config, pairs, frames
    trainsets/<condition>             captures of the train scenes, the condition's curate config, pairs, frames
                                      (and the condition's pairfits, linked in)
    calibration/<condition>           trainsets/target-<regime>, the family (a family file by its hash),
                                      the strength grid, the objective
    trainsets/<calibrated condition>  its calibration output, the captures, pairs, frames
    training/<condition>-s<seed>      the training set, the model (and its config file's hash), the run
                                      overrides (seed included), the probe capture
    testsets/<scene>-<regime>         the capture, the regime, [sparse], clips.frames, clips.per_scene
    refine/<row>-<scene>-<regime>     the test set, the training run or the control row
    metrics2d/..., metrics3d/...      the refined clips, the test set, [metrics], [refit], clips.heldout
    report/                           every output it reads (with its condition, seed, scene, regime)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from morphgs.ablation.conditions import CONTROLS, Condition
from morphgs.ablation.jobs import File, Job, Keyed, Out, job
from morphgs.ablation.scenes import SceneSet, capture_size, resolve_scenes, scene_fingerprint
from morphgs.ablation.study import Study, StudyError

__all__ = ["CALIBRATION_GRID", "FIT_SEED", "PAIRS_SEED", "build_plan"]

PAIRS_SEED = 0   # the training pairs' run seed (the same noise streams for every condition)
FIT_SEED = 0     # sparse fits and re-fits: one seed, every row sees the same test sets
# the calibration stage's strength scan: calibrate's default log grid (2^-4 .. 2^7, two per octave)
CALIBRATION_GRID = tuple(float(2.0 ** (k / 2 - 4)) for k in range(23))


def _model_config(path: str) -> File:
    if path and not Path(path).is_file():
        raise StudyError(f"model.config: {path}: no such model config file")
    return File(path)


def build_plan(study: Study, root: Path, scenes: SceneSet | None = None) -> list[Job]:
    """Every job of the study, upstream first, each keyed by what it reads. Pure: it writes
    nothing and loads nothing heavy (the scene inputs and the model config file are hashed for
    their keys; LPIPS is looked for, not loaded)."""
    from morphgs.ablation.stages import training as T
    from morphgs.ablation.stages import trainsets as TS
    from morphgs.ablation.stages.metrics2d import lpips_status
    from morphgs.curation.plan import FIT_KINDS

    S = study.settings
    sc = scenes or resolve_scenes(study)
    size = capture_size(study)
    jobs: list[Job] = []

    def add(stage: str, name: str, *, meta: dict[str, Any] | None = None, **kwargs: Any) -> Job:
        j = job(root, stage, name, meta=meta, **kwargs)
        jobs.append(j)
        return j

    # 0-1. clean fits of captures given as photos, then captures: per scene (the built-in rooms keep
    # their own z-up orbit: no `up`)
    cap: dict[str, Job] = {}
    clean = {k: S["clean"][k] for k in ("steps", "random_points", "cap_max")}
    for sid in sc.train + sc.test:
        src = sc.sources[sid]
        fp = scene_fingerprint(src)
        fitted = None
        if src.capture is not None:
            fitted = add("cleanfits", sid, capture=Keyed(src.capture, fp), size=size, clean=clean, seed=FIT_SEED,
                         meta={"scene": sid, "min_psnr": float(S["clean"]["min_psnr"])})
        cap[sid] = add("captures", sid, source=Keyed(src, fp), views=int(S["capture"]["views"]),
                       size=size, up=S["capture"]["up"] if src.builtin is None else None,
                       clean_dir=Out(fitted) if fitted is not None else None)

    # 2. training sets: per condition, on the train scenes' captures (a target per regime also when
    # only a calibrated condition needs it: its real pairs are what the family is calibrated against)
    scene_dirs = [Out(cap[s], s) for s in sc.train]
    common = dict(scene_dirs=scene_dirs, pairs_per_scene=int(S["conditions"]["pairs_per_scene"]),
                  frames=int(S["clips"]["frames"]), size=size, seed=PAIRS_SEED, clean=S["conditions"]["clean"])
    regimes = {r.label: r for r in study.regimes}
    calibrated = [c for c in study.conditions if c.kind == "calibrated"]
    curated = [c for c in study.conditions if c.kind != "calibrated"]
    for t in (Condition.target(str(c.regime)) for c in calibrated):  # once per regime, however many calibrate
        if t not in curated:
            curated.append(t)
    tsets: dict[str, Job] = {}
    for cond in curated:
        r = regimes[str(cond.regime)] if cond.kind == "target" else None
        spec = TS.condition_spec(cond.name, blur_sigma=float(S["conditions"]["blur_sigma"]),
                                 regime=r.params if r else None, sparse=S["sparse"])
        keyed = Keyed(spec, TS.key_of(spec))
        # 1b. a fit-based condition fits each training scene in its own job (they spread over the
        # pool or the cluster); the training set links them in and renders the pairs
        fits = [Out(add("pairfits", f"{cond.slug}-{s}", scene_dir=Out(cap[s], s), spec=keyed,
                        meta={"condition": cond.name, "scene": s},
                        **{k: v for k, v in common.items() if k != "scene_dirs"}))
                for s in sc.train] if spec.kind in FIT_KINDS else []
        tsets[cond.name] = add("trainsets", cond.slug, spec=keyed, calibration_dir=None, fits=fits,
                               meta={"condition": cond.name}, **common)

    # 2b. calibration: per calibrated condition (family x regime), against the regime's target set;
    # then its training set, curated with the calibrated strength distribution
    for cond in calibrated:
        target = tsets[Condition.target(str(cond.regime)).name]
        calib = add("calibration", cond.slug, scene_dirs=scene_dirs, real_dir=Out(target, "data"),
                    family=File(str(cond.family)) if cond.family_file else cond.family,
                    grid=list(CALIBRATION_GRID), objective=cond.objective,
                    meta={"condition": cond.name})
        tsets[cond.name] = add("trainsets", cond.slug, spec=cond.slug, calibration_dir=Out(calib), fits=[],
                               meta={"condition": cond.name}, **common)

    # 3. training: per (condition, seed); the CKA probe is the first training scene's capture
    probe = sc.train[0]
    threads = int(S["training"]["threads"])
    model_config = _model_config(S["model"]["config"])
    runs: dict[tuple[str, int], Job] = {}
    for cond in study.conditions:
        for seed in study.seeds:
            runs[cond.name, seed] = add(
                "training", f"{cond.slug}-s{seed}", data=Out(tsets[cond.name], "data"), model=S["model"]["name"],
                model_config=model_config, overrides=T.overrides_for(S["training"], S["model"]["overrides"], seed),
                probe_dir=Out(cap[probe], probe), probe_rows=int(S["training"]["probe_rows"]), threads=threads,
                meta={"condition": cond.name, "seed": seed})

    # 4. test sets: per (test scene, regime)
    tests: dict[tuple[str, str], Job] = {}
    for sid in sc.test:
        for r in study.regimes:
            tests[sid, r.label] = add(
                "testsets", f"{sid}-{r.label}", capture_dir=Out(cap[sid]), regime=r.params, sparse=S["sparse"],
                frames=int(S["clips"]["frames"]), per_scene=int(S["clips"]["per_scene"]), seed=FIT_SEED,
                meta={"scene": sid, "regime": r.label})

    # 5-7. refine every test clip with every model and control row; 2D and 3D metrics of each
    lpips_note = lpips_status(S["metrics"]["lpips"], S["metrics"]["lpips_net"])
    rows: list[tuple[str, str, int | None, Job | None]] = [
        (f"{c.slug}-s{s}", c.name, s, runs[c.name, s]) for c in study.conditions for s in study.seeds]
    rows += [(c, c, None, None) for c in CONTROLS]
    for (sid, rl), test in tests.items():
        for row, cond_name, rseed, run in rows:
            name, meta = f"{row}-{sid}-{rl}", {"scene": sid, "regime": rl, "condition": cond_name, "seed": rseed}
            refined = add("refine", name, testset_dir=Out(test), row=cond_name,
                          run_dir=Out(run, "run") if run else None, window=int(S["training"]["window"]),
                          threads=threads, meta=meta)
            add("metrics2d", name, testset_dir=Out(test), refined_dir=Out(refined), lpips_note=lpips_note,
                lpips_net=S["metrics"]["lpips_net"], eflow=bool(S["metrics"]["eflow"]), threads=threads, meta=meta)
            add("metrics3d", name, testset_dir=Out(test), refined_dir=Out(refined), refit=S["refit"],
                heldout=list(S["clips"]["heldout"]), thresholds=list(S["metrics"]["fscore"]),
                lpips_note=lpips_note, lpips_net=S["metrics"]["lpips_net"], seed=FIT_SEED, threads=threads,
                meta=meta)

    # 8. the report: every output it reads, with what each stands for
    read = ("cleanfits", "trainsets", "calibration", "training", "testsets", "refine", "metrics2d", "metrics3d")
    parts = [(j.ref.stage, Out(j), j.meta) for j in jobs if j.ref.stage in read]
    add("report", "report", parts=parts, conditions=[c.name for c in study.conditions],
        regimes=[r.label for r in study.regimes], lpips_note=lpips_note)
    return jobs
