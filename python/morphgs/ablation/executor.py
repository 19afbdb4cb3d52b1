"""Running a study's jobs (morphgs.ablation.recipe describes them): in this process, in local worker
processes, or as Ray tasks; then publishing the report and logging the run.

- A job starts as soon as every job it reads is finished (not level by level), so two workers
  stay busy while, say, a test set's sparse fit runs beside the training sets.
- Each job is made by `cache.run_stage`: a work folder renamed into place when complete, so a
  killed study loses no finished output and never sees half of one. Worker processes have fixed
  thread counts, so the bytes do not depend on `workers`.
- Each computed job's CPU seconds (user + system of the process that ran it, all its threads --
  torch's and the Rust core's -- and its finished child processes) are measured in that process
  and logged beside its wall seconds in STUDY/runs.jsonl; they change no study output.
- A failed job lets the jobs in flight finish (their outputs are kept), starts nothing new, and
  raises. Ctrl-C or SIGTERM stops the workers at once.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

from morphgs.ablation import cache
from morphgs.ablation.jobs import Job
from morphgs.ablation.study import Study, StudyError, flatten, to_toml
from morphgs.reliability.checksums import CHECKSUMS
from morphgs.trajectory import CropWarning

__all__ = ["SETTINGS_FILE", "check_study_folder", "run_jobs", "run_study"]

SETTINGS_FILE = "study.json"

# what a worker gets of a job: its ref, key inputs, resolved make() arguments and resumability
Task = tuple[cache.StageRef, dict[str, Any], dict[str, Any], bool]


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


def run_study(study: Study, root: Path, *, workers: int = 1, recompute: bool = False, backend: str = "local",
              ray_address: str | None = None, log: Callable[[str], None] | None = None) -> cache.Ledger:
    """Run (or continue) a study in `root`; returns what was computed and reused.

    Args:
        workers: local worker processes (with Ray: CPUs per task = cores // workers).
        recompute: accept a folder made with other settings (recompute what depends on them).
        backend: "local" or "ray" (`ray_address`: a cluster; default: start a local Ray).
    """
    from morphgs.ablation.model_check import check_model_folders
    from morphgs.ablation.recipe import build_plan

    say = log or (lambda m: print(m, file=sys.stderr, flush=True))
    if workers < 1:
        raise StudyError(f"workers must be >= 1, got {workers}")
    if backend not in ("local", "ray"):
        raise StudyError(f"backend must be 'local' or 'ray', got {backend!r}")
    check_model_folders(study)
    jobs = build_plan(study, root)
    check_study_folder(study, root, recompute=recompute)
    ledger = cache.Ledger()
    t_all = time.perf_counter()
    busy = any(not cache.is_done(j.ref) for j in jobs)
    stop_ray = _start_ray(ray_address) if backend == "ray" and busy else None
    try:
        run_jobs(jobs, workers=workers, backend=backend, ledger=ledger, say=say)
    finally:
        if stop_ray is not None:
            stop_ray()
    _publish(jobs, root)
    _write_run_log(root, ledger, time.perf_counter() - t_all, workers)
    return ledger


def run_jobs(jobs: Sequence[Job], *, workers: int, backend: str, ledger: cache.Ledger,
             say: Callable[[str], None]) -> None:
    """Make every job that is not finished yet (`jobs` upstream first, as build_plan gives them),
    each as soon as the jobs it reads are."""
    finished: set[str] = set()
    todo: list[Job] = []
    for j in jobs:
        if cache.usable(j.ref):
            ledger.add(j.ref, "reused", 0.0)
            finished.add(j.ref.key)
        else:
            todo.append(j)
    if not todo:
        return
    stages = sorted({j.ref.stage for j in todo}, key=[j.ref.stage for j in jobs].index)
    say(f"ablate: {len(todo)} job(s) to make ({', '.join(stages)}), {len(jobs) - len(todo)} reused")
    count = [0]

    def done(j: Job, status: str, secs: float, cpu: float | None) -> None:
        ledger.add(j.ref, status, secs, cpu)
        finished.add(j.ref.key)
        count[0] += 1
        say(f"  [{count[0]}/{len(todo)}] {j.ref.stage}/{j.ref.name}: {status} in {secs:.1f} s")

    def ready(waiting: list[Job]) -> list[Job]:
        return [j for j in waiting if all(u.ref.key in finished for u in j.depends_on())]

    threads = max(1, (os.cpu_count() or 1) // workers)
    if backend == "ray":
        _run_ray(todo, threads, ready, done)
    elif workers == 1 or len(todo) == 1:
        for j in todo:  # upstream first already
            done(j, *make(_task(j)))
    else:
        _run_pool(todo, workers, threads, ready, done)


def make(task: Task) -> tuple[str, float, float | None]:
    """Make one stage output, in this process or a worker: ("computed" | "reused", wall seconds,
    CPU seconds of this process and its children while it ran, or None when reused)."""
    from morphgs.ablation.stages import stage_module

    ref, inputs, kwargs, resumable = task
    mod = stage_module(ref.stage)
    cpu0 = _cpu_seconds()
    with warnings.catch_warnings():
        # the study said it once per capture while checking its inputs; a job (of the capture or of
        # the study's own copy of it, at the study size) would say it again
        warnings.simplefilter("ignore", CropWarning)
        _, status, secs = cache.run_stage(ref, inputs, lambda w: mod.make(w, **kwargs), resumable=resumable)
    cpu = _cpu_seconds() - cpu0 if status == "computed" else None
    return status, secs, cpu


def _cpu_seconds() -> float:
    """User + system CPU seconds so far of this process (every thread of it) and of its child
    processes that have ended and been waited for."""
    try:
        import resource
    except ImportError:  # Windows: no getrusage; os.times has no children there (zeros)
        t = os.times()
        return t.user + t.system + t.children_user + t.children_system
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _task(j: Job) -> Task:
    return (j.ref, j.inputs, j.call_kwargs(), j.resumable)


def _init_worker(threads: int) -> None:
    os.environ["MORPHGS_NUM_THREADS"] = str(threads)


def _ray_make(task: Task, threads: int) -> tuple[str, float, float | None]:
    _init_worker(threads)
    return make(task)


Ready = Callable[[list[Job]], list[Job]]
Done = Callable[[Job, str, float, float | None], None]


def _run_pool(todo: list[Job], workers: int, threads: int, ready: Ready, done: Done) -> None:
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(threads,))
    waiting = list(todo)
    running: dict[Future[tuple[str, float, float | None]], Job] = {}
    try:
        while waiting or running:
            for j in ready(waiting):
                waiting.remove(j)
                running[pool.submit(make, _task(j))] = j
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                done(running.pop(f), *f.result())
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM (Preempted): stop now
        _stop_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_ray(todo: list[Job], threads: int, ready: Ready, done: Done) -> None:
    import ray

    remote = ray.remote(num_cpus=threads, max_retries=0)(_ray_make)
    waiting = list(todo)
    running: dict[Any, Job] = {}
    while waiting or running:
        for j in ready(waiting):
            waiting.remove(j)
            running[remote.remote(_task(j), threads)] = j
        finished, _ = ray.wait(list(running), num_returns=1)
        for r in finished:
            done(running.pop(r), *ray.get(r))


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the pool's workers: a stop (Ctrl-C, or SIGTERM sent to this process alone, as
    Kubernetes and `kill PID` do) must not wait for the jobs in flight, which can run for many
    minutes. Their outputs are written atomically under temporary names, so the rerun makes them
    again; nothing finished is lost. (The executor keeps no public list of its processes; its
    `_processes` map is the one handle there is.)"""
    procs = getattr(pool, "_processes", None) or {}
    for proc in list(procs.values()):
        if proc.is_alive():
            proc.terminate()
    for proc in list(procs.values()):
        proc.join(timeout=10)


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


def _publish(jobs: Sequence[Job], root: Path) -> None:
    """Copy the report stage's files to the top of the study folder (table.md, results.*, plots/)."""
    rep = next(j for j in jobs if j.ref.stage == "report").ref.path
    for p in sorted(rep.iterdir()):
        if p.name in (cache.STAGE_FILE, CHECKSUMS):
            continue
        dst = root / p.name
        tmp = root / f".{p.name}.tmp"
        if p.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(p, tmp)
            shutil.rmtree(dst, ignore_errors=True)
            os.rename(tmp, dst)
        else:
            shutil.copyfile(p, tmp)
            os.replace(tmp, dst)


def _write_run_log(root: Path, ledger: cache.Ledger, seconds: float, workers: int) -> None:
    rec = {"time": time.strftime("%Y-%m-%dT%H:%M:%S"), "workers": workers, "seconds": round(seconds, 2),
           "counts": ledger.counts(), "stage_seconds": ledger.seconds(),
           "stage_cpu_seconds": ledger.cpu_seconds(), "jobs": ledger.entries}
    with open(root / "runs.jsonl", "a", encoding="utf-8") as f:
        f.write(json.dumps(rec, sort_keys=True) + "\n")
