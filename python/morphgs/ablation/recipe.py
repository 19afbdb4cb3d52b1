"""The ablation recipe, top to bottom (docs/ablation.md). Every stage output lives under
STUDY/<stage>/<name>-<key>/, and its key hashes everything it reads:

    captures/<scene>     key(scene file or built-in parameters, capture.views, capture.size)
    trainsets/<cond>     key(condition, captures of the train scenes, pairs_per_scene, frames, [sparse] for targets)
    calibration/<cond>   key(trainsets/target-<regime>, family, the strength grid)   (calibrated:FAMILY-<regime>)
    trainsets/<cond>     key(calibration/<cond>, captures, pairs_per_scene, frames)  (curated with its distribution)
    training/<cond>-s<seed>  key(trainsets/<cond>, model, its config file, its overrides, [training], seed, probe capture)
    testsets/<scene>-<regime>  key(captures/<scene>, regime, [sparse], clips.frames, clips.per_scene)
    refine/<row>-<scene>-<regime>  key(testsets/..., training/... or the control row)
    metrics2d/..., metrics3d/...  key(refine/..., testsets/..., [metrics], [refit], clips.heldout)
    report/              key(every metrics output, the severities, the CKA curves)

A rerun reuses every output whose key is there (a finished study does no work); a changed
setting changes the keys of what reads it, and only those are recomputed. Jobs of one level run
in worker processes (`workers`), each with fixed thread counts, so the bytes do not depend on it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs.ablation import cache
from morphgs.ablation.scenes import SceneSet, capture_size, resolve_scenes, scene_fingerprint
from morphgs.ablation.study import (Study, StudyError, calibrated_family, condition_regime, flatten, target_name,
                                    to_toml)
from morphgs.reliability.checksums import CHECKSUMS

__all__ = ["Job", "build_plan", "check_study_folder", "run_study"]

STAGES = ("captures", "trainsets", "calibration", "training", "testsets", "refine", "metrics2d", "metrics3d", "report")
PAIRS_SEED = 0   # the training pairs' run seed (the same noise streams for every condition)
FIT_SEED = 0     # sparse fits and re-fits: one seed, every row sees the same test sets
# the calibration stage's strength scan: calibrate's default log grid (2^-4 .. 2^7, two per octave)
CALIBRATION_GRID = tuple(float(2.0 ** (k / 2 - 4)) for k in range(23))


@dataclass(frozen=True)
class Job:
    """One stage output to make: where, its key inputs, and the stage function's arguments."""

    ref: cache.StageRef
    inputs: dict[str, Any]
    kwargs: dict[str, Any]
    resumable: bool = False
    level: int = 0
    meta: dict[str, Any] = field(default_factory=dict)


def _file_hash(path: str) -> str | None:
    import hashlib

    if not path:
        return None
    p = Path(path)
    if not p.is_file():
        raise StudyError(f"model.config: {p}: no such model config file")
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _slug(name: str) -> str:
    """A condition as a folder name (a JSON path's slashes and the like become '_')."""
    from morphgs.ablation.report import label

    return re.sub(r"[^A-Za-z0-9.@+_-]+", "_", label(name)).strip("._") or "condition"


def build_plan(study: Study, root: Path, scenes: SceneSet | None = None) -> list[Job]:
    """Every job of the study, level by level, each keyed by what it reads (pure: no files are
    written; only the scene inputs and the model config file are read for their keys)."""
    from morphgs.ablation.stages import training as T
    from morphgs.ablation.stages import trainsets as TS
    from morphgs.ablation.stages.refine import CONTROLS
    from morphgs.ablation.stages.metrics2d import lpips_status

    S = study.settings
    sc = scenes or resolve_scenes(study)
    size = capture_size(study)
    jobs: list[Job] = []

    def add(stage: str, name: str, inputs: dict[str, Any], level: int, resumable: bool = False,
            **kw: Any) -> Job:
        ref = cache.ref_for(root, stage, name, inputs)
        job = Job(ref, inputs, {k: v for k, v in kw.items() if k != "meta"}, resumable, level, kw.get("meta", {}))
        jobs.append(job)
        return job

    # 1. captures: per scene
    cap: dict[str, Job] = {}
    for sid in sc.train + sc.test:
        src = sc.sources[sid]
        inputs = {"scene": scene_fingerprint(src), "views": S["capture"]["views"], "size": list(size)}
        if src.builtin is None:  # the built-in rooms keep their own z-up orbit (and their keys)
            inputs["up"] = S["capture"]["up"]
        cap[sid] = add("captures", sid, inputs, 0, source=src, views=int(S["capture"]["views"]), size=size,
                       up=S["capture"]["up"])

    # 2. training sets: per condition, on the train scenes' captures (a target per regime also when
    # only a calibrated condition needs it: its real pairs are what the family is calibrated against)
    train_dirs = [str(cap[s].ref.path / s) for s in sc.train]
    regimes = {target_name(r): r for r in study.regimes}
    ts_common = {"captures": [cap[s].ref.key for s in sc.train], "pairs_per_scene": S["conditions"]["pairs_per_scene"],
                 "frames": S["clips"]["frames"], "size": list(size), "seed": PAIRS_SEED}
    ts_kw: dict[str, Any] = dict(scene_dirs=train_dirs, pairs_per_scene=int(S["conditions"]["pairs_per_scene"]),
                                 frames=int(S["clips"]["frames"]), size=size, seed=PAIRS_SEED)
    calibrated = [c for c in study.conditions if calibrated_family(c) is not None]
    needed = [c for c in study.conditions if calibrated_family(c) is None]
    needed += [t for t in regimes if t not in needed and any(condition_regime(c) == regimes[t].label for c in calibrated)]
    tsets: dict[str, Job] = {}
    for cond in needed:
        r = regimes.get(cond) if cond.startswith("target-") else None
        spec = TS.condition_spec(cond, blur_sigma=float(S["conditions"]["blur_sigma"]),
                                 regime=r.params if r else None, sparse=S["sparse"])
        tsets[cond] = add("trainsets", _slug(cond), {"spec": spec.as_dict(), **ts_common}, 1,
                          resumable=r is not None, spec=spec, meta={"condition": cond}, **ts_kw)

    # 2b. calibration: per calibrated condition (family x regime), against the regime's target set;
    # then its training set, curated with the calibrated strength distribution
    calib: dict[str, Job] = {}
    for cond in calibrated:
        fam, tgt = calibrated_family(cond), tsets[f"target-{condition_regime(cond)}"]
        calib[cond] = add("calibration", _slug(cond),
                          {"target": tgt.ref.key, "family": fam, "grid": list(CALIBRATION_GRID), "lpips": False},
                          2, scene_dirs=train_dirs, real_dir=str(tgt.ref.path / "data"), family=fam,
                          grid=list(CALIBRATION_GRID), meta={"condition": cond})
        tsets[cond] = add("trainsets", _slug(cond), {"calibration": calib[cond].ref.key, **ts_common}, 3,
                          spec=_slug(cond), calibration_dir=str(calib[cond].ref.path), meta={"condition": cond},
                          **ts_kw)

    # 3. training: per (condition, seed); the CKA probe is the first training scene's capture
    probe = cap[sc.train[0]]
    model_hash = _file_hash(S["model"]["config"])
    runs: dict[tuple[str, int], Job] = {}
    for cond in study.conditions:
        for seed in study.seeds:
            over = T.overrides_for(S["training"], S["model"]["overrides"], seed)
            runs[cond, seed] = add(
                "training", f"{_slug(cond)}-s{seed}",
                {"trainset": tsets[cond].ref.key, "model": S["model"]["name"], "model_config": model_hash,
                 "overrides": over, "probe": probe.ref.key, "probe_rows": S["training"]["probe_rows"]},
                4 if cond in calib else 3, resumable=True, data=str(tsets[cond].ref.path / "data"), model=S["model"]["name"],
                model_config=S["model"]["config"], overrides=over, probe_dir=str(probe.ref.path / sc.train[0]),
                probe_rows=int(S["training"]["probe_rows"]), threads=int(S["training"]["threads"]),
                meta={"condition": cond, "seed": seed})

    # 4. test sets: per (test scene, regime)
    tests: dict[tuple[str, str], Job] = {}
    for sid in sc.test:
        for r in study.regimes:
            tests[sid, r.label] = add(
                "testsets", f"{sid}-{r.label}",
                {"capture": cap[sid].ref.key, "regime": r.params, "sparse": S["sparse"], "frames": S["clips"]["frames"],
                 "per_scene": S["clips"]["per_scene"], "seed": FIT_SEED},
                3, resumable=True, capture_dir=str(cap[sid].ref.path), regime=r.params, sparse=S["sparse"],
                frames=int(S["clips"]["frames"]), per_scene=int(S["clips"]["per_scene"]), seed=FIT_SEED,
                meta={"scene": sid, "regime": r.label})

    # 5-7. refine every test clip with every model and control row; 2D and 3D metrics of each
    threads = int(S["training"]["threads"])
    lp_note = lpips_status(S["metrics"]["lpips"], S["metrics"]["lpips_net"])
    rows: list[tuple[str, int | None, Job | None]] = [(c, s, runs[c, s]) for c in study.conditions
                                                      for s in study.seeds]
    rows += [(c, None, None) for c in CONTROLS]
    for (sid, rl), tj in tests.items():
        for cond, rseed, rj in rows:
            row = f"{_slug(cond)}-s{rseed}" if rseed is not None else cond
            meta = {"scene": sid, "regime": rl, "condition": cond, "seed": rseed}
            ref_in = {"testset": tj.ref.key, "run": rj.ref.key if rj else None, "row": cond,
                      "window": S["training"]["window"]}
            fj = add("refine", f"{row}-{sid}-{rl}", ref_in, 5, testset_dir=str(tj.ref.path), row=cond,
                     run_dir=str(rj.ref.path / "run") if rj else None, window=int(S["training"]["window"]),
                     threads=threads, meta=meta)
            add("metrics2d", f"{row}-{sid}-{rl}",
                {"refined": fj.ref.key, "testset": tj.ref.key, "lpips": S["metrics"]["lpips"],
                 "lpips_net": S["metrics"]["lpips_net"], "lpips_available": lp_note is None, "eflow": S["metrics"]["eflow"]},
                6, testset_dir=str(tj.ref.path), refined_dir=str(fj.ref.path), lpips=S["metrics"]["lpips"],
                lpips_net=S["metrics"]["lpips_net"], eflow=bool(S["metrics"]["eflow"]), threads=threads, meta=meta)
            add("metrics3d", f"{row}-{sid}-{rl}",
                {"refined": fj.ref.key, "testset": tj.ref.key, "refit": S["refit"], "heldout": S["clips"]["heldout"],
                 "fscore": S["metrics"]["fscore"], "lpips_available": lp_note is None,
                 "lpips_net": S["metrics"]["lpips_net"], "seed": FIT_SEED},
                6, resumable=True, testset_dir=str(tj.ref.path), refined_dir=str(fj.ref.path), refit=S["refit"],
                heldout=list(S["clips"]["heldout"]), thresholds=list(S["metrics"]["fscore"]), lpips_note=lp_note,
                lpips_net=S["metrics"]["lpips_net"], seed=FIT_SEED, threads=threads, meta=meta)

    # 8. the report: every metrics output, the severities and the CKA curves
    read = ("metrics2d", "metrics3d", "trainsets", "training", "calibration")
    parts = {j.ref.path.name: j.ref.key for j in jobs if j.ref.stage in read}
    add("report", "report", {"parts": parts, "settings": flatten(S)}, 7, study=study, root=str(root),
        jobs=[(j.ref.stage, str(j.ref.path), j.meta) for j in jobs if j.ref.stage in (*read, "testsets", "refine")],
        lpips_note=lp_note)
    return jobs


# ---- the study folder ----

SETTINGS_FILE = "study.json"


def check_study_folder(study: Study, root: Path, *, recompute: bool) -> None:
    """Refuse a study folder made with other settings (naming the keys that differ) unless
    `recompute`; then record this study's settings in it (study.json, study.toml)."""
    f = root / SETTINGS_FILE
    now = flatten(study.settings)
    if f.is_file() and not recompute:
        was = json.loads(f.read_text(encoding="utf-8"))["settings"]
        diff = sorted(k for k in set(was) | set(now) if was.get(k) != now.get(k))
        if diff:
            shown = "; ".join(f"{k}: {was.get(k, '(absent)')} -> {now.get(k, '(absent)')}" for k in diff[:8])
            more = f" and {len(diff) - 8} more" if len(diff) > 8 else ""
            raise StudyError(f"{root}: this study folder was made with other settings ({shown}{more}); "
                             "pass --recompute to recompute what depends on them, or choose another --out")
    root.mkdir(parents=True, exist_ok=True)
    cache.write_json_atomic(f, {"settings": now, "preset": study.preset})
    tmp = root / ".study.toml.tmp"
    tmp.write_text(to_toml(study), encoding="utf-8")
    os.replace(tmp, root / "study.toml")


# ---- running the jobs ----

def _run_job(job: Job) -> tuple[str, float]:
    """Make one stage output (in this process or a worker)."""
    import importlib

    if job.ref.stage == "report":
        from morphgs.ablation import report as mod
    else:
        mod = importlib.import_module(f"morphgs.ablation.stages.{job.ref.stage}")
    _, status, secs = cache.run_stage(job.ref, job.inputs, lambda w: mod.make(w, **job.kwargs),
                                      resumable=job.resumable)
    return status, secs


def _init_worker(threads: int) -> None:
    os.environ["MORPHGS_NUM_THREADS"] = str(threads)


def _ray_job(job: Job, threads: int) -> tuple[str, float]:
    os.environ["MORPHGS_NUM_THREADS"] = str(threads)
    return _run_job(job)


def _run_level(todo: list[Job], workers: int, backend: str, done: Callable[[Job, str, float], None]) -> None:
    """Run one level's jobs: in this process, in local worker processes, or as Ray tasks."""
    threads = max(1, (os.cpu_count() or 1) // workers)
    if backend == "ray":
        import ray

        remote = ray.remote(num_cpus=threads, max_retries=0)(_ray_job)
        refs = {remote.remote(j, threads): j for j in todo}
        waiting = list(refs)
        while waiting:
            ready, waiting = ray.wait(waiting, num_returns=1)
            for r in ready:
                done(refs[r], *ray.get(r))
    elif workers == 1 or len(todo) == 1:
        for j in todo:
            done(j, *_run_job(j))
    else:
        ctx = __import__("multiprocessing").get_context("spawn")
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                                   initargs=(threads,))
        try:
            futs = {pool.submit(_run_job, j): j for j in todo}
            pending = set(futs)
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    done(futs[f], *f.result())
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM (Preempted): stop now
            _stop_workers(pool)
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the pool's workers: a stop (Ctrl-C, or SIGTERM sent to this process alone, as
    Kubernetes and `kill PID` do) must not wait for the jobs in flight, which can run for many
    minutes (a failed job still lets the others finish and keep their outputs). Their outputs are written atomically under
    temporary names, so the rerun makes them again; nothing finished is lost."""
    procs = getattr(pool, "_processes", None) or {}  # the executor's own pid -> Process map
    for proc in list(procs.values()):
        if proc.is_alive():
            proc.terminate()
    for proc in list(procs.values()):
        proc.join(timeout=10)


def run_study(study: Study, root: Path, *, workers: int = 1, recompute: bool = False, backend: str = "local",
              ray_address: str | None = None, log: Callable[[str], None] | None = None) -> cache.Ledger:
    """Run (or continue) a study in `root`; returns what was computed and reused.

    Args:
        workers: local worker processes per level (with Ray: CPUs per task = cores // workers).
        recompute: accept a folder made with other settings (recompute what depends on them).
        backend: "local" or "ray" (`ray_address`: a cluster; default: start a local Ray).
    """
    say = log or (lambda m: print(m, file=sys.stderr, flush=True))
    if workers < 1:
        raise StudyError(f"workers must be >= 1, got {workers}")
    if backend not in ("local", "ray"):
        raise StudyError(f"backend must be 'local' or 'ray', got {backend!r}")
    from morphgs.ablation.model_check import check_model_folders

    check_model_folders(study)
    jobs = build_plan(study, root)
    check_study_folder(study, root, recompute=recompute)
    ledger = cache.Ledger()
    t_all = time.perf_counter()
    busy = any(not cache.is_done(j.ref) for j in jobs)
    stop_ray = _start_ray(ray_address) if backend == "ray" and busy else None
    try:
        _run_levels(jobs, workers, backend, ledger, say)
    finally:
        if stop_ray is not None:
            stop_ray()
    _publish(jobs, root)
    _write_run_log(root, ledger, time.perf_counter() - t_all, workers)
    return ledger


def _start_ray(address: str | None) -> Callable[[], None] | None:
    """Connect to (or start) Ray once for the whole study; returns its shutdown when we started it."""
    try:
        import ray
    except ImportError:
        raise ImportError("--backend ray needs Ray: pip install 'morphgs[ray]'") from None
    if ray.is_initialized():
        return None
    if address:
        ray.init(address=address, log_to_driver=False)
    else:
        ray.init(num_cpus=os.cpu_count(), log_to_driver=False, include_dashboard=False)
    return ray.shutdown  # type: ignore[no-any-return]


def _run_levels(jobs: list[Job], workers: int, backend: str, ledger: cache.Ledger,
                say: Callable[[str], None]) -> None:
    for level in sorted({j.level for j in jobs}):
        todo = []
        for j in (j for j in jobs if j.level == level):
            if cache.usable(j.ref):
                ledger.add(j.ref, "reused", 0.0)
            else:
                todo.append(j)
        if not todo:
            continue
        say(f"ablate: {len(todo)} job(s) of stage(s) {', '.join(sorted({j.ref.stage for j in todo}))}")

        def done(j: Job, status: str, secs: float) -> None:
            ledger.add(j.ref, status, secs)
            say(f"  {j.ref.stage}/{j.ref.name}: {status} in {secs:.1f} s")

        _run_level(todo, workers, backend, done)


def _publish(jobs: list[Job], root: Path) -> None:
    """Copy the report stage's files to the top of the study folder (table.md, results.*, plots/)."""
    rep = next(j for j in jobs if j.ref.stage == "report").ref.path
    for p in sorted(rep.iterdir()):
        if p.name in (cache.STAGE_FILE, CHECKSUMS):
            continue
        dst = root / p.name
        if p.is_dir():
            tmp = root / f".{p.name}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(p, tmp)
            shutil.rmtree(dst, ignore_errors=True)
            os.rename(tmp, dst)
        else:
            tmp = root / f".{p.name}.tmp"
            shutil.copyfile(p, tmp)
            os.replace(tmp, dst)


def _write_run_log(root: Path, ledger: cache.Ledger, seconds: float, workers: int) -> None:
    rec = {"time": time.strftime("%Y-%m-%dT%H:%M:%S"), "workers": workers, "seconds": round(seconds, 2),
           "counts": ledger.counts(), "stage_seconds": ledger.seconds(), "jobs": ledger.entries}
    with open(root / "runs.jsonl", "a", encoding="utf-8") as f:
        f.write(json.dumps(rec, sort_keys=True) + "\n")
