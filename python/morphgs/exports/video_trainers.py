"""Exports for the video trainers that pair a target clip with a control clip: DiffSynth-Studio,
VideoX-Fun and TheDenk's Wan ControlNet scripts. In all three the clean render is the target video
and the corrupted render is the control (conditioning) video; docs/exports.md gives each layout and
the source file of the contract it follows.
"""

from __future__ import annotations

import csv
import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from morphgs.exports.common import (DEFAULT_PROMPT, Captions, ExportSummary, progress_bar, write_export_json,
                                    write_json)
from morphgs.exports.encode import clip_to_mp4, default_workers, ordered_map, reference_png
from morphgs.exports.source import PairEntry, check_trainer_shapes, encoded_size, load_pairs
from morphgs.exports.staging import staged_dir

__all__ = ["export_diffsynth", "export_thedenk", "export_videox_fun"]


@dataclass(frozen=True)
class _Layout:
    """Where a trainer wants the target (clean) and control (corrupted) MP4 of a pair, relative to OUT."""

    trainer: str
    clean: Callable[[PairEntry], str]
    control: Callable[[PairEntry], str]


_DIFFSYNTH = _Layout("DiffSynth-Studio", lambda e: f"videos/{e.key}.mp4", lambda e: f"control_videos/{e.key}.mp4")
_VIDEOX_FUN = _Layout("VideoX-Fun", lambda e: f"train/{e.key}.mp4", lambda e: f"control/{e.key}.mp4")
_THEDENK = _Layout("TheDenk's Wan ControlNet", lambda e: f"{e.split}/videos/{e.key}.mp4",
                   lambda e: f"{e.split}/controlnet_videos/{e.key}.mp4")


def _write_clips(tmp: Path, entries: Sequence[PairEntry], layout: _Layout, *, fps: float, crf: int,
                 workers: int | None, show_progress: bool) -> None:
    """Encode (or copy) the clean and corrupted clip of every pair, clips in parallel."""
    jobs = [(e, side, tmp / (layout.clean(e) if side == "clean" else layout.control(e)))
            for e in entries for side in ("clean", "corrupted")]

    def run(job: tuple[PairEntry, str, Path]) -> None:
        clip_to_mp4(job[0], job[1], job[2], fps=fps, crf=crf)

    bar = progress_bar(len(jobs), enabled=show_progress, unit="clip")
    try:
        for _ in ordered_map(run, jobs, workers=workers or default_workers()):
            bar.update(1)
    finally:
        bar.close()


def _by_split(entries: Sequence[PairEntry]) -> dict[str, list[PairEntry]]:
    out: dict[str, list[PairEntry]] = {}
    for e in entries:
        out.setdefault(e.split, []).append(e)
    return out


def _run(fmt: str, layout: _Layout, dataset: str | os.PathLike[str], out: str | os.PathLike[str], *,
         overwrite: bool, configs: Sequence[str] | None, fps: float, crf: int, workers: int | None,
         show_progress: bool, options: dict[str, Any],
         write_metadata: Callable[[Path, Sequence[PairEntry]], None]) -> ExportSummary:
    t0 = time.perf_counter()
    root, entries = load_pairs(dataset, configs=configs)
    msgs = check_trainer_shapes(entries, trainer=layout.trainer)
    with staged_dir(out, root, overwrite=overwrite) as tmp:
        _write_clips(tmp, entries, layout, fps=fps, crf=crf, workers=workers, show_progress=show_progress)
        write_metadata(tmp, entries)
        counts = write_export_json(tmp, fmt=fmt, source=root, entries=entries,
                                   options={**options, "fps": fps, "crf": crf}, warnings=msgs)
    return ExportSummary(fmt, Path(out), counts, msgs, {"seconds": time.perf_counter() - t0})


def export_diffsynth(
    dataset: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    configs: Sequence[str] | None = None,
    prompt: str = DEFAULT_PROMPT,
    captions: Mapping[str, str] | None = None,
    reference_frame: int | None = None,
    fps: float = 16,
    crf: int = 18,
    workers: int | None = None,
    progress: bool = True,
) -> ExportSummary:
    """DiffSynth-Studio's video dataset: `metadata.csv` (train) and `metadata_test.csv` (test) with
    columns `video` (clean MP4), `prompt`, `control_video` (corrupted MP4) and, with
    `reference_frame`, `reference_image` (that clean frame as a PNG), paths relative to OUT.

    Train with `--dataset_base_path OUT --dataset_metadata_path OUT/metadata.csv
    --data_file_keys "video,control_video[,reference_image]" --extra_inputs "control_video[,reference_image]"`.

    Args:
        dataset: a `morphgs curate` folder. out: the export folder (must not exist or be empty).
        overwrite: replace an existing export at `out`.
        configs: only pairs of these config names.
        prompt: the text of every pair, unless `captions` (pair id or scene id -> text) has one.
        reference_frame: also write clean frame N of each pair as its reference image.
        fps, crf: H.264 frame rate and quality of the MP4s encoded from frames.
        workers: clips encoded at once (the native thread count by default).
        progress: a progress bar on stderr.

    Returns:
        An `ExportSummary` (pairs per split, warnings).

    Raises:
        FileNotFoundError, ExportError: see `load_pairs` and `staged_dir`; a reference frame past a clip.
    """
    text = Captions(prompt, captions)

    def metadata(tmp: Path, entries: Sequence[PairEntry]) -> None:
        cols = ["video", "prompt", "control_video"] + (["reference_image"] if reference_frame is not None else [])
        for split, items in _by_split(entries).items():
            rows = []
            for e in items:
                row = {"video": _DIFFSYNTH.clean(e), "prompt": text(e), "control_video": _DIFFSYNTH.control(e)}
                if reference_frame is not None:
                    rel = f"reference_images/{e.key}.png"
                    reference_png(e, reference_frame, tmp / rel)
                    row["reference_image"] = rel
                rows.append(row)
            name = "metadata.csv" if split == "train" else f"metadata_{split}.csv"
            with open(tmp / name, "w", newline="", encoding="utf-8") as f:
                w = csv.DictWriter(f, fieldnames=cols, lineterminator="\n")
                w.writeheader()
                w.writerows(rows)

    return _run("diffsynth", _DIFFSYNTH, dataset, out, overwrite=overwrite, configs=configs, fps=fps, crf=crf,
                workers=workers, show_progress=progress, write_metadata=metadata,
                options={"prompt": prompt, "captions": bool(captions), "reference_frame": reference_frame})


def export_videox_fun(
    dataset: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    configs: Sequence[str] | None = None,
    prompt: str = DEFAULT_PROMPT,
    captions: Mapping[str, str] | None = None,
    fps: float = 16,
    crf: int = 18,
    workers: int | None = None,
    progress: bool = True,
) -> ExportSummary:
    """VideoX-Fun's control dataset: clean MP4s in `train/`, corrupted ones under the same names in
    `control/`, and `metadata.json` (train) / `metadata_test.json` (test): lists of `{"file_path",
    "control_file_path", "text", "type": "video", "width", "height"}`, paths relative to OUT.

    Train with `--train_data_dir OUT --train_data_meta OUT/metadata.json`. Arguments as
    `export_diffsynth` (no reference image: VideoX-Fun takes it from the clip, `--control_ref_image`).
    """
    text = Captions(prompt, captions)

    def metadata(tmp: Path, entries: Sequence[PairEntry]) -> None:
        for split, items in _by_split(entries).items():
            rows = []
            for e in items:
                w, h = encoded_size(e.width, e.height)
                rows.append({"file_path": _VIDEOX_FUN.clean(e), "control_file_path": _VIDEOX_FUN.control(e),
                             "text": text(e), "type": "video", "width": w, "height": h})
            name = "metadata.json" if split == "train" else f"metadata_{split}.json"
            (tmp / name).write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")

    return _run("videox-fun", _VIDEOX_FUN, dataset, out, overwrite=overwrite, configs=configs, fps=fps, crf=crf,
                workers=workers, show_progress=progress, write_metadata=metadata,
                options={"prompt": prompt, "captions": bool(captions)})


def export_thedenk(
    dataset: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    configs: Sequence[str] | None = None,
    prompt: str = DEFAULT_PROMPT,
    captions: Mapping[str, str] | None = None,
    fps: float = 16,
    crf: int = 18,
    workers: int | None = None,
    progress: bool = True,
) -> ExportSummary:
    """TheDenk's Wan ControlNet layout, per split: `SPLIT/videos/KEY.mp4` (clean: the input of
    `prepare_vae_latents.py --input_video_dir`), `SPLIT/controlnet_videos/KEY.mp4` (corrupted: the
    `--controlnet_video_dir` that `train_controlnet.py`'s `ControlnetDataset` reads by basename) and
    `SPLIT/captions.csv` (columns `video`, `caption`: the `--csv_path` of `prepare_text_embeddings.py`),
    plus `SPLIT/clips.json` (frames and size, for the latent script's `--sample_n_frames`,
    `--width`, `--height`). Arguments as `export_diffsynth`.
    """
    text = Captions(prompt, captions)

    def metadata(tmp: Path, entries: Sequence[PairEntry]) -> None:
        for split, items in _by_split(entries).items():
            with open(tmp / split / "captions.csv", "w", newline="", encoding="utf-8") as f:
                w = csv.writer(f, lineterminator="\n")
                w.writerow(["video", "caption"])
                w.writerows([f"{e.key}.mp4", text(e)] for e in items)
            write_json(tmp / split / "clips.json", {
                f"{e.key}.mp4": {"frames": e.frames, "width": encoded_size(e.width, e.height)[0],
                                 "height": encoded_size(e.width, e.height)[1], "pair_id": e.pair_id}
                for e in items})

    return _run("thedenk", _THEDENK, dataset, out, overwrite=overwrite, configs=configs, fps=fps, crf=crf,
                workers=workers, show_progress=progress, write_metadata=metadata,
                options={"prompt": prompt, "captions": bool(captions)})
