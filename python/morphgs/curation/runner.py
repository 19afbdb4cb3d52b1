"""`morphgs.curate(...)`: plan, skip what is done, make the rest (in-process, in local worker
processes, or on Ray), append the manifest, and report."""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import socket
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import ExitStack
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs.curation import manifest
from morphgs.curation.fits import underfit_stops
from morphgs.curation.plan import ConfigSpec, PairJob, TrajectoryOptions, check_up, make_plan, parse_config, uses_orbit
from morphgs.curation.sources import BUILTIN_GAUSSIANS, SceneSource, builtin_sources, discover
from morphgs.curation.worker import OutputOptions, make_pair, tmp_root
from morphgs.reliability import folder_lock

__all__ = ["CurateSummary", "curate"]

# Fields of a manifest record that must match the job for the record to count as this job done.
_IDENTITY = ("seed", "frames", "resolution", "config", "depth", "video", "background")


@dataclass
class CurateSummary:
    """What a curate run did. `ok` is False when a scene failed."""

    out: Path
    planned: int = 0
    done: int = 0
    skipped: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    records: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    dry_run: bool = False

    @property
    def ok(self) -> bool:
        return not self.failed

    def text(self) -> str:
        lines = [f"morphgs curate: {self.done} pairs made, {self.skipped} already done, "
                 f"{len(self.failed)} scene(s) failed, of {self.planned} planned, in {self.seconds:.1f} s "
                 f"-> {self.out}"]
        for sid, msg in sorted(self.failed.items()):
            lines.append(f"  FAILED {sid}: {msg}")
        return "\n".join(lines)


# ---- per-process scene cache (workers load each scene once) ----
_CACHE: dict[str, Any] = {}


def _scene_for(source: SceneSource, resolution: tuple[int, int]) -> tuple[Any, Any, float]:
    key = repr((source, resolution))  # the whole source: two runs in one process may share scene ids
    hit = _CACHE.get(key)
    if hit is None:
        _CACHE.clear()
        t0 = time.perf_counter()
        try:
            scene = source.load()
            recorded = source.load_cameras(resolution)
            hit = (scene, recorded, time.perf_counter() - t0, None)
        except Exception as e:  # noqa: BLE001 - reported per scene by the caller
            hit = (None, None, 0.0, e)
        _CACHE[key] = hit
        load_s = hit[2]
    else:
        load_s = 0.0
    if hit[3] is not None:
        raise hit[3]
    return hit[0], hit[1], load_s


def _run_job(job: PairJob, out_dir: str, opts: OutputOptions) -> dict[str, Any]:
    scene, recorded, load_s = _scene_for(job.source, (job.width, job.height))
    return make_pair(job, scene, recorded, Path(out_dir), opts, load_seconds=load_s)


def _init_worker(threads: int) -> None:
    os.environ["MORPHGS_NUM_THREADS"] = str(threads)


def _clean_stale_tmp(out_dir: Path) -> None:
    """Remove temporaries of dead processes of this host (runs killed mid-pair)."""
    root = tmp_root(out_dir)
    if not root.is_dir():
        return
    host = socket.gethostname()
    for d in root.iterdir():
        h, _, rest = d.name.rpartition("-")[0].rpartition("-")
        try:
            pid = int(rest)
        except ValueError:
            continue
        if h != host:
            continue
        try:
            os.kill(pid, 0)
            alive = pid != os.getpid()
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if not alive:
            shutil.rmtree(d, ignore_errors=True)


def _matches(rec: dict[str, Any], job: PairJob, opts: OutputOptions) -> bool:
    want = {"seed": job.seed, "frames": job.frames, "resolution": [job.width, job.height],
            "config": job.config.as_dict(), "depth": opts.depth, "video": opts.video,
            "background": list(opts.background)}
    photos = opts.trajectory.kind == "photos" and job.config.kind != "cross"
    return (all(rec.get(k) == want[k] for k in _IDENTITY) and _same_up(rec, job, opts.trajectory)
            and (rec.get("clean_source") == "photos") == photos)


def _same_up(rec: dict[str, Any], job: PairJob, traj: TrajectoryOptions) -> bool:
    """Whether a finished pair turned around the up this run would use (records written before
    the up was recorded had +z orbits). The "scene" rule is compared as a rule: its vector needs
    the scene, and it is the same for the same scene file."""
    import numpy as np

    from morphgs.trajectory import scene_up

    cross_cameras = job.config.kind == "cross" and job.source.cameras is not None  # along its capture
    if cross_cameras or not uses_orbit(job.source.cameras is not None, traj):
        return rec.get("up") is None
    got = rec.get("up", [0.0, 0.0, 1.0])
    if got is None:
        return False
    if job.source.builtin is not None:
        return bool(np.allclose(got, [0.0, 0.0, 1.0]))
    if job.source.cameras is not None:  # an orbit around where the recorded cameras look
        return rec.get("up_rule") == "cameras"
    if traj.up == "scene":
        return rec.get("up_rule") == "scene"
    return bool(np.allclose(got, scene_up(None, traj.up)[0]))


class _PlainProgress:
    """A stand-in for tqdm (not installed): one stderr line per finished pair with rate and ETA."""

    def __init__(self, total: int, enabled: bool, desc: str = "curate", unit: str = "pair") -> None:
        self.total, self.n, self.enabled, self.t0 = total, 0, enabled, time.perf_counter()
        self.desc, self.unit = desc, unit

    def update(self, k: int = 1) -> None:
        self.n += k
        if self.enabled:
            dt = time.perf_counter() - self.t0
            rate = self.n / dt if dt > 0 else 0.0
            eta = (self.total - self.n) / rate if rate > 0 else float("nan")
            print(f"{self.desc}: {self.n}/{self.total} {self.unit}s, {rate:.2f} {self.unit}s/s, ETA {eta:.0f} s",
                  file=sys.stderr)

    def write(self, msg: str, file: Any = None) -> None:
        print(msg, file=file or sys.stderr)

    def close(self) -> None:
        pass


def progress_bar(total: int, enabled: bool, desc: str = "curate", unit: str = "pair") -> Any:
    """curate's progress bar on stderr: tqdm, or one plain line per step without it."""
    try:
        from tqdm import tqdm
    except ImportError:
        return _PlainProgress(total, enabled, desc, unit)
    return tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, disable=not enabled,
                dynamic_ncols=True, smoothing=0.1)


def curate(
    scenes: Iterable[str | os.PathLike[str]] = (),
    out: str | os.PathLike[str] = "out/dataset",
    *,
    configs: Sequence[str | ConfigSpec] = ("morphological",),
    pairs_per_scene: int = 2,
    frames: int = 49,
    resolution: tuple[int, int] = (832, 480),
    seed: int = 0,
    test_fraction: float = 0.1,
    split_seed: int = 0,
    blur_sigma: float = 2.0,
    depth: bool = False,
    video: bool = False,
    fps: int = 16,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    trajectory: str = "auto",
    stride: int | None = None,
    orbit_arc_degrees: float = 60.0,
    fov_y_degrees: float = 50.0,
    up: str = "file",
    chunk: int = 8,
    workers: int = 1,
    backend: str = "local",
    ray_address: str | None = None,
    shard_index: int = 0,
    num_shards: int = 1,
    builtin_scenes: int = 2,
    builtin_gaussians: int = BUILTIN_GAUSSIANS,
    dry_run: bool = False,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    wait: bool = False,
) -> CurateSummary:
    """Curate clean/corrupted training pairs from 3DGS scenes (SPEC §5; docs/curation.md).

    Args:
        scenes: scene files or folders (see morphgs.curation.sources); none = built-in samples.
        out: dataset folder (created; reruns resume in it).
        configs: corruption per pair set: preset names, "NAME@SCALE", "blur2d[@SIGMA]", JSON
            files, or ConfigSpec.
        pairs_per_scene: K pairs per scene and config.
        frames: F frames per pair; resolution: (W, H).
        seed: run seed (pair seeds derive from it, the scene id and the pair index).
        test_fraction, split_seed: the deterministic train/test split by scene.
        blur_sigma: sigma (pixels) of "blur2d" when not given in the config.
        depth: also write depth EXRs. video: MP4s instead of PNG frames. fps: video rate.
        background: RGB background. trajectory: "auto", "cameras", "orbit" or "photos" (runs of
            the capture's photos, which are the clean side). stride: clip stride along recorded
            cameras or photos. orbit_arc_degrees, fov_y_degrees: orbit paths.
        up: the world up of orbits around scene files (`trajectory.scene_up` rules: "file", the
            loaders' RDF convention, -y; "scene"; "+x" ... "-z"; "X,Y,Z"). Built-in sample
            scenes orbit around +z whatever it says. Recorded in each record's "up".
        chunk: frames rendered per pass (the writer encodes one chunk while the next renders).
        workers: local worker processes (spawned); backend: "local" or "ray".
        shard_index, num_shards: this process's share of the jobs (cluster job arrays).
        builtin_scenes, builtin_gaussians: the sample scenes used when `scenes` is empty.
        dry_run: plan and report only. progress: tqdm bar on stderr. log: message sink (stderr).
        wait: when another process writes `out`, wait for it instead of raising FolderBusyError.

    Returns:
        CurateSummary (`ok` is False when a scene failed).

    Raises:
        ValueError: bad arguments, or `out` holds pairs made with other settings.
        morphgs.reliability.FolderBusyError: another process (not a shard of this run) writes
        `out` (names its pid, host and start time).
    """
    args = dict(locals())  # every argument, by name
    del args["wait"]
    with ExitStack() as stack:
        if not dry_run:
            stack.enter_context(folder_lock(out, command="curate", shard=(shard_index, num_shards), wait=wait,
                                            say=log))
        return _curate(**args)


def _curate(*, scenes: Iterable[str | os.PathLike[str]], out: str | os.PathLike[str],
            configs: Sequence[str | ConfigSpec], pairs_per_scene: int, frames: int, resolution: tuple[int, int],
            seed: int, test_fraction: float, split_seed: int, blur_sigma: float, depth: bool, video: bool, fps: int,
            background: tuple[float, float, float], trajectory: str, stride: int | None, orbit_arc_degrees: float,
            fov_y_degrees: float, up: str, chunk: int, workers: int, backend: str, ray_address: str | None,
            shard_index: int, num_shards: int, builtin_scenes: int, builtin_gaussians: int, dry_run: bool,
            progress: bool, log: Callable[[str], None] | None) -> CurateSummary:
    """`curate`, with the folder locked (see there)."""
    say = log or (lambda m: print(m, file=sys.stderr))
    t_begin = time.perf_counter()
    out_dir = Path(out)
    scene_list = [str(s) for s in scenes]
    if scene_list:
        sources, problems = discover(scene_list)
    else:
        sources, problems = builtin_sources(builtin_scenes, n_gaussians=builtin_gaussians), []
    specs = [c if isinstance(c, ConfigSpec) else parse_config(c, blur_sigma=blur_sigma) for c in configs]
    if not specs:
        raise ValueError("at least one config is needed")
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    opts = OutputOptions(depth=depth, video=video, fps=fps, background=tuple(background),  # type: ignore[arg-type]
                         chunk=chunk, trajectory=TrajectoryOptions(trajectory, stride, orbit_arc_degrees,
                                                                   fov_y_degrees, check_up(up)),
                         fit_stops=underfit_stops(specs, seed))
    jobs = make_plan(sources, specs, pairs_per_scene=pairs_per_scene, run_seed=seed, frames=frames,
                     resolution=tuple(resolution), test_fraction=test_fraction,  # type: ignore[arg-type]
                     split_seed=split_seed, shard_index=shard_index, num_shards=num_shards)
    summary = CurateSummary(out=out_dir, planned=len(jobs), dry_run=dry_run)
    for inp, msg in problems:
        summary.failed[inp] = msg
        say(f"morphgs curate: skipping {inp}: {msg}")

    existing = manifest.load(out_dir)
    todo: list[PairJob] = []
    for job in jobs:
        rec = existing.get(job.pair_id)
        if rec is not None and manifest.is_complete(out_dir, rec):
            if not _matches(rec, job, opts):
                raise ValueError(f"{out_dir} already holds pair {job.pair_id} made with other settings "
                                 f"(seed/frames/resolution/config/depth/video/background/up); use another --out")
            summary.skipped += 1
        else:
            todo.append(job)

    if dry_run:
        for src in sources:
            sj = [j for j in jobs if j.source.id == src.id]
            split = sj[0].split if sj else "-"
            say(f"scene {src.id} [{split}]: {src.describe()}")
        for job in jobs:
            state = "todo" if job in todo else "done"
            say(f"  {job.pair_id}  split={job.split} seed={job.seed} {job.frames}x{job.width}x{job.height} [{state}]")
        say(f"plan: {len(jobs)} pairs ({len(todo)} to make, {summary.skipped} done), "
            f"{len(sources)} scene(s), configs {', '.join(s.label for s in specs)}, "
            f"shard {shard_index}/{num_shards}")
        summary.seconds = time.perf_counter() - t_begin
        return summary

    out_dir.mkdir(parents=True, exist_ok=True)
    _clean_stale_tmp(out_dir)
    man_path = out_dir / manifest.manifest_name(shard_index, num_shards)
    redo = {job.pair_id for job in todo}
    removed = manifest.compact(man_path, drop=redo)
    if removed:
        say(f"morphgs curate: {man_path}: rewrote it with one line per finished pair ({removed} duplicate or "
            "unfinished line(s) removed)")
    written: set[str] = set()
    bar = progress_bar(len(todo), progress)
    failed_scenes: set[str] = set()

    def finished(job: PairJob, rec: dict[str, Any] | None, err: BaseException | None) -> None:
        if err is not None:
            if job.source.id not in failed_scenes:
                failed_scenes.add(job.source.id)
                summary.failed[job.source.id] = f"{type(err).__name__}: {err}"
                bar.write(f"morphgs curate: scene {job.source.id} failed ({type(err).__name__}: {err}); "
                          "skipping its remaining pairs", file=sys.stderr)
        else:
            assert rec is not None
            if rec["pair_id"] not in written:  # one record per pair id
                manifest.append(man_path, rec)
                written.add(rec["pair_id"])
            summary.done += 1
            summary.records.append(rec)
        bar.update(1)

    try:
        if backend == "ray":
            _run_ray(todo, out_dir, opts, workers, ray_address, finished, failed_scenes)
        elif workers == 1:
            for job in todo:
                if job.source.id in failed_scenes:
                    bar.update(1)
                    continue
                try:
                    rec = _run_job(job, str(out_dir), opts)
                except Exception as e:  # noqa: BLE001 - a bad scene must not stop the others
                    finished(job, None, e)
                else:
                    finished(job, rec, None)
        else:
            _run_processes(todo, out_dir, opts, workers, finished, failed_scenes)
    finally:
        bar.close()
        summary.seconds = time.perf_counter() - t_begin
    return summary


def _threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // workers)


def _run_processes(todo: list[PairJob], out_dir: Path, opts: OutputOptions, workers: int,
                   finished: Callable[[PairJob, Any, Any], None], failed: set[str]) -> None:
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                             initargs=(_threads_per_worker(workers),)) as pool:
        try:
            _drain(pool, todo, out_dir, opts, finished)
        except BaseException:  # Ctrl-C, SIGTERM: abandon the pairs in progress (their temporaries go next run)
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.terminate()
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def _drain(pool: ProcessPoolExecutor, todo: list[PairJob], out_dir: Path, opts: OutputOptions,
           finished: Callable[[PairJob, Any, Any], None]) -> None:
    futures: dict[Future[dict[str, Any]], PairJob] = {
        pool.submit(_run_job, job, str(out_dir), opts): job for job in todo}
    pending = set(futures)
    while pending:
        done, pending = wait(pending, return_when=FIRST_COMPLETED)
        for fut in done:
            job = futures[fut]
            err = fut.exception()
            finished(job, None if err else fut.result(), err)
            if err is not None:  # do not spend time on the rest of a failed scene
                for f, j in futures.items():
                    if j.source.id == job.source.id and f in pending and f.cancel():
                        pending.discard(f)
                        finished(j, None, err)


def _run_ray(todo: list[PairJob], out_dir: Path, opts: OutputOptions, workers: int, address: str | None,
             finished: Callable[[PairJob, Any, Any], None], failed: set[str]) -> None:
    try:
        import ray
    except ImportError:
        raise ImportError("--backend ray needs Ray: pip install 'morphgs[ray]'") from None
    started = not ray.is_initialized()
    if started:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=os.cpu_count(), log_to_driver=False, include_dashboard=False)
    try:
        cpus = int(ray.available_resources().get("CPU", 1))
        threads = max(1, min(_threads_per_worker(workers), cpus))
        remote = ray.remote(num_cpus=threads, max_retries=0)(_ray_job)
        refs = {remote.remote(job, str(out_dir), opts, threads): job for job in todo}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                job = refs[ref]
                try:
                    rec = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - reported per scene
                    finished(job, None, getattr(e, "cause", None) or e)
                else:
                    finished(job, rec, None)
                    continue
                if job.source.id in failed:  # do not spend time on the rest of a failed scene
                    for r in [r for r in pending if refs[r].source.id == job.source.id]:
                        ray.cancel(r)
    finally:
        if started:
            ray.shutdown()


def _ray_job(job: PairJob, out_dir: str, opts: OutputOptions, threads: int) -> dict[str, Any]:
    os.environ.setdefault("MORPHGS_NUM_THREADS", str(threads))
    return _run_job(job, out_dir, opts)
