"""`morphgs fit DATA... --out ROOT`: one fit per capture, under an output root (docs/fit.md,
"Many scenes").

    ROOT/<scene>/        a run folder per capture (the `morphgs fit` layout), which `morphgs
                         curate ROOT/*/` reads as it is: point_cloud/iteration_N/point_cloud.ply
                         and the INRIA cameras.json of the views
    ROOT/fits.json       every capture: its input, run folder, status ("done", "failed"), the
                         error of a failed one, held-out PSNR, Gaussians, seconds

Scene names are the capture folder names (made filesystem-safe; two captures of one name get a
suffix from a hash of their resolved path, as curate does). Captures run in local worker
processes (spawned, each with its share of the cores: MORPHGS_NUM_THREADS); a capture whose
run folder holds a finished fit (fit.json) is skipped, an unfinished one resumes from its
checkpoint, and a failing capture is recorded and the others go on.
"""

from __future__ import annotations

import glob
import hashlib
import json
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs.reliability import folder_lock

__all__ = ["ManyResult", "expand_inputs", "fit_many"]


@dataclass
class ManyResult:
    """What `fit_many` did: one record per capture (see the module docs)."""

    root: Path
    scenes: list[dict[str, Any]] = field(default_factory=list)

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [s for s in self.scenes if s["status"] == "failed"]

    def text(self) -> str:
        done = [s for s in self.scenes if s["status"] == "done"]
        lines = [f"morphgs fit: {len(done)} of {len(self.scenes)} captures fitted under {self.root}"]
        for s in self.failed:
            lines.append(f"  failed: {s['scene']} ({s['input']}): {s['error']}")
        return "\n".join(lines)


def expand_inputs(inputs: Sequence[str]) -> list[str]:
    """Arguments as given, with glob patterns expanded (sorted) and `@FILE` replaced by the
    paths listed in FILE (one a line; blank lines and `#` comments skipped)."""
    out: list[str] = []
    for raw in inputs:
        if raw.startswith("@"):
            lines = Path(raw[1:]).read_text(encoding="utf-8").splitlines()
            out.extend(expand_inputs([ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]))
        elif any(ch in raw for ch in "*?[") and not Path(raw).exists():
            out.extend(sorted(glob.glob(raw)))
        else:
            out.append(raw)
    return out


def _names(inputs: Sequence[str]) -> list[str]:
    from morphgs.curation.sources import slug

    def base(p: str) -> str:
        q = Path(p).resolve()
        return slug(q.parent.name if q.is_file() else q.name)

    bases = [base(p) for p in inputs]
    return [b if bases.count(b) == 1 else f"{b}-{hashlib.sha256(str(Path(p).resolve()).encode()).hexdigest()[:8]}"
            for b, p in zip(bases, inputs)]


def _fit_one(data: str, run: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """One capture, in a worker: a record for fits.json (errors caught and recorded)."""
    from morphgs.fit.run import fit

    t = time.perf_counter()
    try:
        res = fit(data, run, progress=False, **kwargs)
    except (Exception, KeyboardInterrupt) as e:  # noqa: BLE001 - one failed capture must not stop the rest
        first = str(e).splitlines()[0] if str(e) else ""
        return {"status": "failed", "error": f"{type(e).__name__}: {first}", "seconds": round(time.perf_counter() - t, 1)}
    return {"status": "done", "steps": res.steps, "gaussians": res.gaussians, "heldout_psnr": res.heldout_psnr,
            "ply": str(res.ply), "seconds": round(time.perf_counter() - t, 1)}


def _init_worker(threads: int) -> None:
    os.environ["MORPHGS_NUM_THREADS"] = str(threads)


def _write(root: Path, records: list[dict[str, Any]]) -> None:
    tmp = root / f".fits.json.tmp{os.getpid()}"
    tmp.write_text(json.dumps({"scenes": records}, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, root / "fits.json")


def fit_many(inputs: Sequence[str], root: str | os.PathLike[str], *, workers: int = 1,
             log: Callable[[str], None] | None = None, wait: bool = False, **kwargs: Any) -> ManyResult:
    """Fit every capture of `inputs` (folders or transforms.json files; globs and @FILE lists
    expanded) into `root/<scene>/`; `kwargs` go to `morphgs.fit.fit` (config, views, holdout,
    init, images, downscale, resume). Returns every capture's record; raises only for bad
    arguments (no input, workers < 1) and `FolderBusyError`.

    One process writes `root` at a time (its lock, `root/.morphgs.lock`; `wait`: wait for the
    holder instead of raising), and each scene's run folder keeps its own lock, taken by the
    worker that fits it (waiting too with `wait`)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    paths = expand_inputs(inputs)
    if not paths:
        raise ValueError(f"no capture matches {list(inputs)}")
    with folder_lock(root, command="fit", wait=wait):
        return _fit_many(paths, Path(root), workers=workers, log=log, kwargs={**kwargs, "wait": wait})


def _fit_many(paths: list[str], out: Path, *, workers: int, log: Callable[[str], None] | None,
              kwargs: dict[str, Any]) -> ManyResult:
    """`fit_many` with the root locked."""
    out.mkdir(parents=True, exist_ok=True)
    names = _names(paths)
    records: list[dict[str, Any]] = [{"scene": n, "input": p, "run": str(out / n), "status": "pending"}
                                     for n, p in zip(names, paths)]
    say = log or (lambda m: None)
    todo = []
    for r in records:
        done = Path(r["run"]) / "fit.json"
        if done.is_file() and kwargs.get("resume", True):
            s = json.loads(done.read_text(encoding="utf-8"))
            r.update(status="done", skipped=True, steps=s.get("steps"), gaussians=s.get("gaussians"),
                     heldout_psnr=s.get("heldout_psnr"))
        elif not Path(r["input"]).exists():
            r.update(status="failed", error=f"FileNotFoundError: {r['input']}: no such file or folder")
        else:
            todo.append(r)
    _write(out, records)
    threads = max(1, (os.cpu_count() or 1) // workers)
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                             initargs=(threads,)) as pool:
        running: dict[Future[dict[str, Any]], dict[str, Any]] = {}
        for r in todo:
            running[pool.submit(_fit_one, r["input"], r["run"], kwargs)] = r
        while running:
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                r = running.pop(f)
                try:
                    r.update(f.result())
                except Exception as e:  # noqa: BLE001 - a worker that died (killed, out of memory)
                    r.update(status="failed", error=f"worker died: {type(e).__name__}: {e}")
                say(f"{r['scene']}: {r['status']}" + (f" ({r['error']})" if r["status"] == "failed" else
                                                      f", held-out PSNR {r.get('heldout_psnr')}"))
                _write(out, records)
    return ManyResult(out, records)
