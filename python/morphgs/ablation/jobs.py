"""Jobs and their keys: a stage output's key is derived from the stage call's own arguments, as
huggingface/datasets fingerprints a transform (`fingerprint_transform` with `ignore_kwargs` and a
version), so an argument cannot reach a stage without reaching its key.

`job(root, stage, name, meta=..., **kwargs)` makes the `Job` of one call of
`stages.<stage>.make(work, **kwargs)`:

- every parameter of `make()` must be given (a missing or unknown one raises at once);
- each argument is keyed by its value, except the stage's `IGNORE` list (thread counts and the
  like, which do not change the bytes);
- an upstream output, `Out(job, "sub/folder")`, contributes that job's key (and the sub-path) and
  reaches `make()` as the path; a file, `File(path)`, its sha256; a value that is not plain
  JSON, `Keyed(value, fingerprint)`, the fingerprint it is given (a scene source: its files'
  hashes); any other type is refused rather than keyed by its repr;
- the stage module's `VERSION` is in the key: bump it whenever the stage's output changes, and
  the stage and everything that reads it is made again, nothing else;
- a job's level is one more than its deepest upstream job's (0 without any).
"""

from __future__ import annotations

import hashlib
import inspect
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs.ablation import cache
from morphgs.ablation.stages import stage_module

__all__ = ["File", "Job", "Keyed", "Out", "fingerprint", "job", "keyed_parameters", "resolve", "upstream"]


@dataclass(frozen=True)
class Out:
    """A path inside an upstream job's output folder (keyed by that job's key)."""

    job: Job
    sub: str = ""


@dataclass(frozen=True)
class File:
    """A file read by a stage, keyed by its contents (sha256); an empty path is no file."""

    path: str

    def sha256(self) -> str | None:
        if not self.path:
            return None
        h = hashlib.sha256()
        with open(self.path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()


@dataclass(frozen=True)
class Keyed:
    """A value that is not plain data, keyed by the fingerprint it comes with."""

    value: Any
    key: Any


@dataclass(frozen=True)
class Job:
    """One stage output to make: where (its ref, whose key derives from `inputs`), the arguments
    of the stage's `make()` (with Out/File/Keyed markers; `resolve` turns them into values), its
    level and what the report needs to know of it (`meta`)."""

    ref: cache.StageRef
    inputs: dict[str, Any]
    kwargs: dict[str, Any]
    resumable: bool
    level: int
    meta: dict[str, Any] = field(default_factory=dict)

    def call_kwargs(self) -> dict[str, Any]:
        """The arguments `make()` gets: every marker resolved."""
        return {k: resolve(v) for k, v in self.kwargs.items()}

    def depends_on(self) -> list[Job]:
        """The upstream jobs whose outputs this one reads (each once, in argument order)."""
        seen: dict[str, Job] = {}
        for u in upstream(self.kwargs):
            seen.setdefault(u.ref.key, u)
        return list(seen.values())


def fingerprint(value: Any) -> Any:
    """The JSON a value contributes to a key (raises TypeError for a type with no defined key)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Out):
        return {"out": value.job.ref.key, "sub": value.sub}
    if isinstance(value, File):
        return {"file_sha256": value.sha256()}
    if isinstance(value, Keyed):
        return fingerprint(value.key)
    if isinstance(value, (list, tuple)):
        return [fingerprint(v) for v in value]
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"a keyed dict must have string keys, got {sorted(map(repr, value))}")
        return {k: fingerprint(v) for k, v in value.items()}
    raise TypeError(f"no key is defined for a {type(value).__name__} ({value!r:.80}): pass plain data, "
                    "or wrap it in Out, File or Keyed")


def resolve(value: Any) -> Any:
    """A marker's run-time value: an Out's path, a File's path, a Keyed value (recursively)."""
    if isinstance(value, Out):
        return str(value.job.ref.path / value.sub) if value.sub else str(value.job.ref.path)
    if isinstance(value, File):
        return value.path
    if isinstance(value, Keyed):
        return value.value
    if isinstance(value, list):
        return [resolve(v) for v in value]
    if isinstance(value, tuple):
        return tuple(resolve(v) for v in value)
    if isinstance(value, dict):
        return {k: resolve(v) for k, v in value.items()}
    return value


def upstream(value: Any) -> Iterator[Job]:
    """The jobs a (nested) argument reads through Out markers."""
    if isinstance(value, Out):
        yield value.job
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from upstream(v)
    elif isinstance(value, dict):
        for v in value.values():
            yield from upstream(v)


def keyed_parameters(stage: str) -> tuple[list[str], list[str]]:
    """(keyed, ignored): the parameters of `stages.<stage>.make()` after `work`, split by the
    stage's IGNORE list (which must name parameters of make())."""
    mod = stage_module(stage)
    params = list(inspect.signature(mod.make).parameters)[1:]
    ignored = list(getattr(mod, "IGNORE", ()))
    stray = sorted(set(ignored) - set(params))
    if stray:
        raise TypeError(f"stages.{stage}.IGNORE names no parameter of make(): {stray}")
    return [p for p in params if p not in ignored], ignored


def job(root: Path, stage: str, name: str, *, meta: dict[str, Any] | None = None, **kwargs: Any) -> Job:
    """The Job of `stages.<stage>.make(work, **kwargs)` under `root` (see the module docstring)."""
    mod = stage_module(stage)
    keyed, ignored = keyed_parameters(stage)
    missing, unknown = sorted(set(keyed + ignored) - set(kwargs)), sorted(set(kwargs) - set(keyed + ignored))
    if missing or unknown:
        raise TypeError(f"stages.{stage}.make(): missing argument(s) {missing}, unknown argument(s) {unknown}")
    inputs = {k: fingerprint(kwargs[k]) for k in keyed}
    ref = cache.ref_for(root, stage, name, inputs, version=int(mod.VERSION))
    levels = [u.level for u in upstream(kwargs)]
    return Job(ref, inputs, dict(kwargs), bool(getattr(mod, "RESUMABLE", False)), 1 + max(levels, default=-1),
               dict(meta or {}))
