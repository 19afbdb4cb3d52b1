"""The real 3DGS fits behind the `sparse`, `underfit` and `cross` configs (docs/curation.md,
"Real-fit pairs"; docs/fit.md): made once, cached, shared by every pair that needs them.

    OUT/fits/<scene>/<label>-<W>x<H>-seed<S>-<hash>/        sparse:K, sparse-n:N, cross:P
        data/transforms.json, data/images/      the training (and scoring) views as fitted
        views.json                              capture size, training and held-out views, images or renders
        run/                                    the morphgs fit run folder (resumable)
        cost.json                               wall seconds: preparing the views, the fit calls
    OUT/fits/<scene>/underfit-<W>x<H>-seed<S>-<hash>/       underfit:F, one folder for every F
        data/, views.json, run/, cost.json      as above; run/ is the full-length fit, advanced
                                                to each stop step in turn and checkpointed there
        snapshots/step_NNNNNN/                  point_cloud.ply and snapshot.json of a stop step
        branches/step_NNNNNN/run/               a fit from step 0 to a stop step the shared run
                                                had already passed (the same bytes, its own cost)

- `sparse`: the training views are every K-th capture view or N spread evenly
  (`sparse.split_views`), fitted to the end of the schedule.
- `cross`: the first round(P x n) capture views, fitted to the end; the pairs are rendered along
  the rest of the capture (`sparse.cross_path`).
- `underfit`: every capture view but up to 8 held-out ones, the schedule of the full fit
  (`steps`), stopped at round(F x steps): the state the full fit has at that step, not a
  shorter schedule (`morphgs.fit.fit(until=...)`). The folder's key leaves F out, so every F of
  a scene shares one run; a curate run stops it at each of its fractions in ascending order
  (`OutputOptions.fit_stops`) and keeps a snapshot at each.

Cost: `cost.json` adds up the wall seconds of making the fit's views (renders of the clean scene,
or reading and scaling photos) and of every fit call that finished (a call killed before its end
is not counted). A fit's `seconds` in the manifest is that total up to its state (for an underfit
stop, the shared run's seconds up to that step: what the stop would cost alone).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsError
from morphgs.camera import Cameras
from morphgs.curation import sparse

__all__ = ["fit_config", "fit_scene", "schedule_key", "underfit_stops"]

_CACHE: dict[str, tuple[Any, dict[str, Any]]] = {}


def fit_config(params: dict[str, Any], label: str, seed: int) -> Any:
    """The FitConfig of a fit config's params: the `sparse` preset, its "fit" overrides, its
    "steps" (the full schedule's length), seeded with the run seed."""
    from morphgs.fit import FitConfig

    cfg = FitConfig.preset("sparse")
    overrides = dict(params.get("fit", {}))
    if "steps" in params:
        overrides["steps"] = int(params["steps"])
    if overrides:
        cfg = FitConfig.from_dict({**cfg.to_dict(), **overrides}, source=f"config {label}")
    cfg.seed = int(seed)
    return cfg


def schedule_key(cfg: Any) -> str:
    """What makes two underfit configs share one run: their full fit's settings."""
    return hashlib.sha256(json.dumps(cfg.to_dict(), sort_keys=True).encode()).hexdigest()[:10]


def underfit_stops(specs: Any, seed: int) -> tuple[tuple[str, int], ...]:
    """(schedule_key, stop step) of every underfit config among `specs` (ConfigSpecs) of a run
    seeded `seed`: `OutputOptions.fit_stops`."""
    from morphgs.curation.plan import stop_step

    out = set()
    for c in specs:
        if c.kind == "underfit":
            cfg = fit_config(c.params, c.label, seed)
            out.add((schedule_key(cfg), stop_step(c.params["fraction"], cfg.steps)))
    return tuple(sorted(out))


def _fit_dir(out_dir: Path, job: Any, fit_cfg: Any, up: list[float] | None) -> Path:
    """The cache folder of a fit; `up` (the capture orbit's up, None when the views are recorded
    cameras or the built-in room orbit) is part of its key, so another --up fits again. An
    underfit folder's key leaves the fraction out (every fraction shares the run)."""
    kind = job.config.kind
    config = {"kind": kind} if kind == "underfit" else job.config.as_dict()
    key: dict[str, Any] = {"config": config, "fit": fit_cfg.to_dict(), "size": [job.width, job.height],
                           "seed": job.run_seed, "scene": job.source.describe()}
    if up is not None:
        key["up"] = [round(v, 9) for v in up]
    h = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:10]
    label = "underfit" if kind == "underfit" else job.config.label
    return out_dir / "fits" / job.source.id / f"{label}-{job.width}x{job.height}-seed{job.run_seed}-{h}"


class _Cost:
    """cost.json of a fit folder: {"prep": seconds making its views (null: not measured, a
    folder from before costs were kept), "run": seconds of the finished calls of run/, "step":
    the step run/ reached}."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / "cost.json"
        try:
            self.d = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            self.d = {"prep": None, "run": 0.0, "step": 0}

    def add(self, **kw: float) -> None:
        for k, v in kw.items():
            self.d[k] = (self.d.get(k) or 0.0) + v
        self.save()

    def save(self) -> None:
        tmp = self.path.with_name(f".cost.json.tmp{os.getpid()}")
        tmp.write_text(json.dumps(self.d) + "\n", encoding="utf-8")
        os.replace(tmp, self.path)

    def total(self, run_seconds: float | None = None) -> float | None:
        """prep + `run_seconds` (default: the run's), None when the prep was not measured."""
        if self.d.get("prep") is None:
            return None
        return round(float(self.d["prep"]) + float(self.d["run"] if run_seconds is None else run_seconds), 3)


def _prepare(folder: Path, job: Any, scene: Any, recorded: Cameras | None, up: str) -> tuple[dict[str, Any], float]:
    """(views.json of the fit, seconds spent), writing data/ and views.json first when needed
    (those seconds also go to cost.json)."""
    views_file = folder / "views.json"
    data = folder / "data"
    spent = 0.0
    if not (data / "transforms.json").is_file() or not views_file.is_file():
        t0 = time.perf_counter()
        kind, params = job.config.kind, job.config.params
        cams, _ = sparse.capture_for(job, scene, recorded, up)
        sparse.check_split(job.config.label, kind, len(cams), params)
        train, held = sparse.split_views(len(cams), params, kind)
        imgs, vcams, images = sparse.views_images(job.source, scene, cams, train + held)
        sparse.write_data(data, vcams, imgs)
        info: dict[str, Any] = {"capture_views": len(cams), "train": train, "heldout": held, "images": images}
        if kind == "cross":
            info["path_views"] = list(range(sparse.cross_cut(len(cams), params), len(cams)))
        views_file.write_text(json.dumps(info, indent=1) + "\n")
        spent = time.perf_counter() - t0
        cost = _Cost(folder)
        cost.d["prep"] = round(spent, 3)
        cost.save()
    return dict(json.loads(views_file.read_text(encoding="utf-8"))), spent


def _run_fit(data: Path, run: Path, cfg: Any, views: dict[str, Any], until: int | None = None) -> Any:
    """One `morphgs.fit.fit` call on a prepared fit folder (from the start when no checkpoint of
    the run verifies)."""
    from morphgs.fit import FitRunError, fit
    from morphgs.fit.run import random_init_on_purpose

    nt, nh = len(views["train"]), len(views["heldout"])
    tv, hv = list(range(nt)), list(range(nt, nt + nh))
    kw: dict[str, Any] = dict(config=cfg, views=tv, holdout=hv, init="random", progress=False, until=until)
    with random_init_on_purpose():
        try:
            return fit(data, run, **kw)
        except FitRunError as e:
            from morphgs.fit import FitPastError

            if isinstance(e, FitPastError):
                raise
            return fit(data, run, resume=False, **kw)  # no checkpoint of it verifies: fit it from the start


def _info(out_dir: Path, folder: Path, ply: Path, views: dict[str, Any], summary: dict[str, Any], seed: int,
          seconds: float | None, **extra: Any) -> dict[str, Any]:
    info = {"dir": str(folder.relative_to(out_dir)), "ply": str(ply.relative_to(out_dir)),
            "capture_views": views["capture_views"], "train_views": views["train"], "images": views["images"],
            "steps": summary["steps"], "gaussians": summary["gaussians"], "heldout_psnr": summary["heldout_psnr"],
            "heldout_ssim": summary["heldout_ssim"], "heldout_lpips": summary.get("heldout_lpips"), "seed": seed,
            "seconds": seconds}
    if "path_views" in views:
        info["path_views"] = views["path_views"]
    info.update(extra)
    return info


def fit_scene(job: Any, scene: Any, recorded: Cameras | None, out_dir: Path, *, up: str = "file",
              stops: tuple[tuple[str, int], ...] = ()) -> tuple[Any, dict[str, Any], float]:
    """The cached fit of a `sparse`, `cross` or `underfit` job, fitted first when needed:
    (GaussianScene, the manifest's `fit` record, seconds this call spent fitting and preparing
    views: 0 when the fit was cached, or made by another process while this one waited). `up`: the up rule of the capture orbit of a scene file
    without cameras (`trajectory.scene_up`). `stops`: (schedule_key, step) of every underfit
    config of the curate run: an underfit run stops at each of its own on the way, in order."""
    cfg = fit_config(job.config.params, job.config.label, job.run_seed)
    orbit_up = None
    if recorded is None and job.source.builtin is None:
        from morphgs import trajectory

        orbit_up = [float(v) for v in trajectory.scene_up(scene, up)[0]]
    folder = _fit_dir(out_dir, job, cfg, orbit_up)
    target = None
    if job.config.kind == "underfit":
        from morphgs.curation.plan import stop_step

        target = stop_step(job.config.params["fraction"], cfg.steps)
    key = f"{folder}@{target}"
    if key in _CACHE:
        return (*_CACHE[key], 0.0)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one process fits; the others wait and reuse it
        views, spent = _prepare(folder, job, scene, recorded, up)
        if target is None:
            result, info, fitting = _full(out_dir, folder, job, cfg, views)
        else:
            mine = sorted({s for k, s in stops if k == schedule_key(cfg) and s < target} | {target})
            result, info, fitting = _underfit(out_dir, folder, job, cfg, views, mine)
    _CACHE.clear()
    _CACHE[key] = (result, info)
    return result, info, spent + fitting


def _full(out_dir: Path, folder: Path, job: Any, cfg: Any,
          views: dict[str, Any]) -> tuple[Any, dict[str, Any], float]:
    """A sparse or cross fit, to the end of its schedule: (scene, record, seconds spent fitting)."""
    run = folder / "run"
    loaded = sparse._cached_result(run) if (run / "fit.json").is_file() else None
    cost = _Cost(folder)
    spent = 0.0
    if loaded is None:
        print(f"curate: fitting {job.source.id} from {len(views['train'])} of {views['capture_views']} views "
              f"({job.config.label}, {cfg.steps} steps) -> {run}", file=sys.stderr)
        res = _run_fit(folder / "data", run, cfg, views)
        spent = res.seconds
        cost.add(run=round(res.seconds, 3))
        cost.d["step"] = res.steps
        cost.save()
        loaded = sparse._cached_result(run)
        if loaded is None:
            raise MorphgsError(f"sparse fit {run}: its result cannot be read back after fitting")
    summary, result = loaded
    return result, _info(out_dir, folder, run / summary["ply"], views, summary, int(job.run_seed), cost.total()), spent


def _underfit(out_dir: Path, folder: Path, job: Any, cfg: Any, views: dict[str, Any],
              stops: list[int]) -> tuple[Any, dict[str, Any], float]:
    """The shared run advanced to each of `stops` in turn (the last is the job's), a snapshot
    kept at each; a stop the run has already passed without a snapshot is fitted alone from step
    0 in branches/ (the same state, by determinism; its own cost)."""
    import morphgs
    from morphgs.fit import FitPastError

    target = stops[-1]
    spent = 0.0
    for step in stops:
        snap = folder / "snapshots" / f"step_{step:06d}"
        if (snap / "snapshot.json").is_file():
            continue
        cost = _Cost(folder)
        run, shared = folder / "run", True
        if int(cost.d.get("step") or 0) > step:
            run, shared = folder / "branches" / f"step_{step:06d}" / "run", False
        print(f"curate: fitting {job.source.id} from {len(views['train'])} of {views['capture_views']} views to step "
              f"{step} of {cfg.steps} (underfit, {'shared run' if shared else 'alone: the shared run is past it'}) "
              f"-> {run}", file=sys.stderr)
        try:
            res = _run_fit(folder / "data", run, cfg, views, until=step)
        except FitPastError:  # checkpointed past it by a call killed after its checkpoint
            run, shared = folder / "branches" / f"step_{step:06d}" / "run", False
            res = _run_fit(folder / "data", run, cfg, views, until=step)
        spent += res.seconds
        if shared:
            cost.add(run=round(res.seconds, 3))
            cost.d["step"] = res.steps
            cost.save()
            seconds = cost.total()
        else:
            branch = _Cost(run.parent)
            branch.d["prep"] = cost.d.get("prep")
            branch.add(run=round(res.seconds, 3))
            seconds = branch.total()
        snap.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(res.ply, snap / "point_cloud.ply")
        s = {"steps": res.steps, "schedule_steps": cfg.steps, "gaussians": res.gaussians,
             "heldout_psnr": res.heldout_psnr, "heldout_ssim": res.heldout_ssim, "heldout_lpips": res.heldout_lpips,
             "seconds": seconds, "run": "shared" if shared else "branch",
             "run_dir": str(run.relative_to(folder))}
        tmp = snap / ".snapshot.json.tmp"
        tmp.write_text(json.dumps(s, indent=1) + "\n", encoding="utf-8")
        os.replace(tmp, snap / "snapshot.json")
    snap = folder / "snapshots" / f"step_{target:06d}"
    s = json.loads((snap / "snapshot.json").read_text(encoding="utf-8"))
    result = morphgs.load(snap / "point_cloud.ply")
    info = _info(out_dir, folder, snap / "point_cloud.ply", views, s, int(job.run_seed), s["seconds"],
                 schedule_steps=s["schedule_steps"], fraction=job.config.params["fraction"], run=s["run"])
    return result, info, spent
