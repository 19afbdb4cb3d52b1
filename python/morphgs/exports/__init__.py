"""Exports of a curated folder for the trainers people use (also `morphgs export FORMAT DIR OUT`).

```python
from morphgs import exports
exports.export("diffsynth", "data", "data-diffsynth")                  # metadata.csv + MP4s
exports.export("webdataset", "data", "data-wds", shard_bytes=256 * 10**6)
```

| format | what OUT holds | trainer contract |
|---|---|---|
| `diffsynth` | `metadata.csv` / `metadata_test.csv`, `videos/`, `control_videos/` | DiffSynth-Studio `UnifiedDataset` |
| `videox-fun` | `metadata.json` / `metadata_test.json`, `train/`, `control/` | VideoX-Fun `ImageVideoControlDataset` |
| `thedenk` | `SPLIT/videos/`, `SPLIT/controlnet_videos/`, `SPLIT/captions.csv` | TheDenk's `ControlnetDataset` |
| `webdataset` | `train-000000.tar` ..., `index.json` | the `webdataset` package |
| `difix` | `data.json` (paths into the curated folder) | Difix3D's `PairedDataset` |

Every export keeps the manifest's train/test split, writes `OUT/export.json` (source, options, key ->
pair id), is written into a temporary folder and renamed into place (a failed export leaves nothing),
and refuses an existing non-empty OUT unless `overwrite=True`. Video formats warn
(`morphgs.MorphgsWarning`) about frame counts other than 4k+1 and sizes not divisible by 16.
docs/exports.md has the layouts and the sources they follow.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from morphgs.exports.common import DEFAULT_PROMPT, ExportSummary, load_captions, write_export_json
from morphgs.exports.source import ExportError, PairEntry, load_pairs, sample_key
from morphgs.exports.staging import staged_dir
from morphgs.exports.video_trainers import export_diffsynth, export_thedenk, export_videox_fun
from morphgs.exports.wds import export_webdataset, parse_shard_size
from morphgs.reliability import folder_lock

__all__ = [
    "FORMATS",
    "ExportError",
    "ExportSummary",
    "PairEntry",
    "export",
    "export_diffsynth",
    "export_difix",
    "export_thedenk",
    "export_videox_fun",
    "export_webdataset",
    "load_captions",
    "load_pairs",
    "parse_shard_size",
    "sample_key",
]


def export_difix(
    dataset: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    configs: Sequence[str] | None = None,
    prompt: str = DEFAULT_PROMPT,
    relative: bool = False,
    ref_offset: int | None = None,
    progress: bool = True,
) -> ExportSummary:
    """Difix3D's `data.json` in the folder `out` (the logic of `morphgs export-difix`): one entry per
    frame, the corrupted frame as `image`, the clean one as `target_image`, a clean frame half a clip
    away as `ref_image`. Paths point into the curated folder: absolute, or relative to `out` with
    `relative`. Pairs curated with --video cannot be exported (Difix3D reads frames). `progress` is
    accepted like the other formats' and has nothing to show (data.json is written at once).

    Raises:
        FileNotFoundError, ExportError: see `load_pairs` and `staged_dir`; pairs written as video.
    """
    from morphgs.curation.difix import export_difix as write_data_json

    del progress
    root, entries = load_pairs(dataset, configs=configs)
    final = Path(out).absolute()
    with staged_dir(final, root, overwrite=overwrite) as tmp:
        # tmp is a sibling of `out`, so paths relative to it are the paths relative to `out`
        counts = write_data_json(root, tmp / "data.json", prompt=prompt, relative=relative,
                                 configs=list(configs) if configs else None, ref_offset=ref_offset)
        write_export_json(tmp, fmt="difix", source=root, entries=entries, warnings=[],
                          options={"prompt": prompt, "relative": relative, "ref_offset": ref_offset})
    return ExportSummary("difix", Path(out), counts, [])


FORMATS: dict[str, Callable[..., ExportSummary]] = {
    "diffsynth": export_diffsynth,
    "videox-fun": export_videox_fun,
    "thedenk": export_thedenk,
    "webdataset": export_webdataset,
    "difix": export_difix,
}


def export(fmt: str, dataset: str | os.PathLike[str], out: str | os.PathLike[str], *, wait: bool = False,
           **options: Any) -> ExportSummary:
    """Export a curated folder in `fmt` (a key of `FORMATS`) into the folder `out`.

    Args:
        fmt: diffsynth, videox-fun, thedenk, webdataset or difix.
        dataset: a `morphgs curate` folder.
        out: the export folder (must not exist or be empty, unless `overwrite=True`).
        wait: when another process exports into `out`, wait for it instead of raising
            morphgs.reliability.FolderBusyError.
        **options: the keyword arguments of that format's function (`export_diffsynth`, ...).

    Returns:
        An `ExportSummary`.

    Raises:
        ExportError: an unknown format, or see the format's function. TypeError: an option the
        format does not take.
    """
    fn = FORMATS.get(fmt)
    if fn is None:
        raise ExportError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
    t0 = time.perf_counter()
    with folder_lock(Path(out).absolute(), command="export", beside=True, wait=wait):
        summary = fn(dataset, out, **options)
    summary.extra.setdefault("seconds", time.perf_counter() - t0)
    return summary
