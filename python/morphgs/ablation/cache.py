"""The stage cache: every stage output under STUDY/<stage>/<name>-<key>/, where the key is a hash
of everything the stage reads (its arguments, the keys of the stages it reads and the stage's code
version; morphgs.ablation.jobs derives them), as huggingface/datasets fingerprints a transform or
dvc decides what to rerun.

- A finished output holds `stage.json` (its key and inputs) and is only ever made by renaming a
  complete work folder (`.<name>-<key>.work`) into place, so a killed study loses no finished
  stage and never sees half of one.
- A resumable stage (training, fits) keeps its work folder across kills and continues in it; the
  others start their work folder afresh.
- A finished output also holds `checksums.json` (size and sha256 of each file, written last); an
  output that no longer matches it (a truncated or damaged file) is reported with a
  MorphgsWarning, moved aside as `<name>-<key>.damaged` and made again.
- The `Ledger` records what each run computed and reused (STUDY/runs.jsonl), which is how a
  rerun shows that it did no work, with each computed job's wall and CPU seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsWarning
from morphgs.reliability import verify_checksums, write_checksums

__all__ = ["Ledger", "StageRef", "key_of", "run_stage", "write_json_atomic"]

STAGE_FILE = "stage.json"


def key_of(stage: str, inputs: dict[str, Any], *, version: int) -> str:
    """The cache key of a stage output: sha256 of the stage, its code version and its canonical
    JSON inputs (16 hex digits)."""
    text = json.dumps({"stage": stage, "v": version, "inputs": inputs}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


@dataclass(frozen=True)
class StageRef:
    """One stage output: where it lives and its key."""

    stage: str
    name: str
    key: str
    path: Path


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write JSON (sorted keys, fixed formatting) through a temporary file and a rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, sort_keys=True, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)


@dataclass
class Ledger:
    """What a run did, stage by stage: computed or reused, and seconds spent (wall, and CPU where
    the job was computed and its CPU time measured)."""

    entries: list[dict[str, Any]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, ref: StageRef, status: str, seconds: float, cpu_seconds: float | None = None) -> None:
        e: dict[str, Any] = {"stage": ref.stage, "name": ref.name, "key": ref.key, "status": status,
                             "seconds": round(seconds, 3)}
        if cpu_seconds is not None and status == "computed":
            e["cpu_seconds"] = round(cpu_seconds, 3)
        with self.lock:
            self.entries.append(e)

    def counts(self) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {}
        for e in self.entries:
            out.setdefault(e["stage"], {"computed": 0, "reused": 0})[e["status"]] += 1
        return out

    def seconds(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for e in self.entries:
            if e["status"] == "computed":
                out[e["stage"]] = round(out.get(e["stage"], 0.0) + e["seconds"], 3)
        return out

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds per stage, summed over its computed jobs (the same stages as `seconds`; a
        computed job without a measurement counts 0)."""
        out: dict[str, float] = {}
        for e in self.entries:
            if e["status"] == "computed":
                out[e["stage"]] = round(out.get(e["stage"], 0.0) + e.get("cpu_seconds", 0.0), 3)
        return out


def ref_for(root: Path, stage: str, name: str, inputs: dict[str, Any], *, version: int) -> StageRef:
    key = key_of(stage, inputs, version=version)
    return StageRef(stage, name, key, root / stage / f"{name}-{key}")


def is_done(ref: StageRef) -> bool:
    return (ref.path / STAGE_FILE).is_file()


def usable(ref: StageRef) -> bool:
    """Whether `ref` is finished and still matches its checksums. A damaged output is moved aside
    (`<name>-<key>.damaged`, replacing an older one) with a warning, so it is made again."""
    return is_done(ref) and _verified(ref)


def _verified(ref: StageRef) -> bool:
    problem = verify_checksums(ref.path)
    if problem is None:
        return True
    aside = ref.path.with_name(ref.path.name + ".damaged")
    if aside.exists():
        shutil.rmtree(aside)
    os.rename(ref.path, aside)
    warnings.warn(f"{ref.path}: damaged stage output ({problem}); moved to {aside.name} and made again",
                  MorphgsWarning, stacklevel=3)
    return False


def run_stage(ref: StageRef, inputs: dict[str, Any], make: Callable[[Path], None], *,
              resumable: bool = False) -> tuple[StageRef, str, float]:
    """Make `ref` unless it is done: `make(work)` fills a work folder that is then renamed into
    place. Returns (ref, "computed" | "reused", seconds)."""
    if usable(ref):
        return ref, "reused", 0.0
    t0 = time.perf_counter()
    work = ref.path.parent / f".{ref.path.name}.work"
    if work.exists() and not resumable:
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    make(work)
    write_json_atomic(work / STAGE_FILE, {"stage": ref.stage, "name": ref.name, "key": ref.key, "inputs": inputs})
    write_checksums(work)
    if ref.path.exists():  # a folder without stage.json: left by a crash between two renames
        shutil.rmtree(ref.path)
    os.rename(work, ref.path)
    return ref, "computed", time.perf_counter() - t0
