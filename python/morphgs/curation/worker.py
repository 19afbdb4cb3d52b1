"""Making one pair on disk: render in chunks while a writer thread encodes the previous chunk,
write everything into a temporary folder, then rename it into place (atomic on one filesystem).

The manifest line is appended by the coordinating process after the rename (see runner.py), so a
killed run leaves either no folder, a stray temporary, or a complete folder without a manifest
line (redone on the next run) -- never a half-written pair that looks complete.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
import uuid
from types import SimpleNamespace
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.camera import Cameras
from morphgs.curation.plan import FIT_KINDS, PairJob, TrajectoryOptions, job_cameras, job_up, up_rule
from morphgs.pair import Corruption, iter_pair_chunks
from morphgs.rendering import RenderBuffers

__all__ = ["OutputOptions", "PairWriter", "make_pair", "tmp_root"]


@dataclass(frozen=True)
class OutputOptions:
    """What to write per pair and how to render it."""

    depth: bool = False
    video: bool = False
    fps: int = 16
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    chunk: int = 8
    trajectory: TrajectoryOptions = TrajectoryOptions()
    #: (schedule key, step) of every underfit config of the run (`morphgs.curation.fits`): a
    #: shared underfit run stops at each on its way, so its fractions are made in ascending order
    fit_stops: tuple[tuple[str, int], ...] = ()


def tmp_root(out_dir: Path) -> Path:
    return out_dir / ".tmp"


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Render.to_uint8's rule, round(clip(rgb, 0, 1) * 255) (float32, half to even), with one
    scratch buffer instead of three temporaries."""
    buf = np.clip(rgb, 0.0, 1.0)
    buf *= np.float32(255.0)
    np.rint(buf, out=buf)
    return buf.astype(np.uint8)


class PairWriter:
    """Writes frame chunks of one pair (PNG, or MP4 through imageio-ffmpeg) and depth EXRs."""

    def __init__(self, folder: Path, opts: OutputOptions, n_frames: int) -> None:
        self.folder, self.opts, self.n = folder, opts, n_frames
        self.videos: dict[str, Any] = {}
        for side in ("clean", "corrupted"):
            if not opts.video or opts.depth:
                (folder / side).mkdir(parents=True, exist_ok=True)
        if opts.video:
            import imageio.v2 as iio

            for side in ("clean", "corrupted"):
                self.videos[side] = iio.get_writer(
                    str(folder / f"{side}.mp4"), format="FFMPEG", mode="I", fps=opts.fps, codec="libx264",
                    quality=8, macro_block_size=1, ffmpeg_log_level="error",
                    output_params=["-threads", "1"])

    def write(self, start: int, side: str, frames: Any) -> None:
        """Write a chunk (a batched Render) whose first frame is number `start`."""
        from morphgs import _core

        idx = range(start, start + len(frames.rgb))
        if self.opts.video:
            for frame in _to_uint8(frames.rgb):
                self.videos[side].append_data(frame)
        else:  # float32 colour: converted to 8 bits frame by frame inside the parallel PNG writers
            img = frames.rgb if frames.rgb.dtype == np.float32 else _to_uint8(frames.rgb)
            _core._write_png_batch([self.folder / side / f"{i:05d}.png" for i in idx], np.ascontiguousarray(img))
        if self.opts.depth:
            _core._write_exr_batch([self.folder / side / f"{i:05d}.depth.exr" for i in idx],
                                   np.ascontiguousarray(frames.depth, dtype=np.float32))

    def close(self) -> None:
        for v in self.videos.values():
            v.close()
        self.videos.clear()


def _write_json(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def make_pair(
    job: PairJob,
    scene: Any,
    recorded: Cameras | None,
    out_dir: Path,
    opts: OutputOptions,
    *,
    load_seconds: float = 0.0,
) -> dict[str, Any]:
    """Render and write one pair; returns its manifest record (not yet appended)."""
    import morphgs

    t_start = time.perf_counter()
    photos = None
    if opts.trajectory.kind == "photos" and job.config.kind != "cross":  # the clean side is the photos
        from morphgs.curation.photos import photo_run

        cams, photos = photo_run(job.source, recorded, job.index, job.frames, (job.width, job.height),
                                 opts.trajectory.stride)
    else:
        cams = job_cameras(job, scene, recorded, opts.trajectory)
    corruption = Corruption.make(job.config).for_seed(job.seed)
    t0 = time.perf_counter()
    fit_info = None
    fitting = 0.0  # seconds this pair spent fitting (the first pair of a fit makes it)
    if job.config.kind in FIT_KINDS:
        from morphgs.curation.fits import fit_scene

        corrupted_scene, fit_info, fitting = fit_scene(job, scene, recorded, out_dir, up=opts.trajectory.up,
                                                       stops=opts.fit_stops)
    else:
        corrupted_scene = corruption.corrupt_scene(scene, job.seed, cams)
    t_perturb = time.perf_counter() - t0

    tmp = tmp_root(out_dir) / f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    tmp.mkdir(parents=True)
    writer = PairWriter(tmp, opts, len(cams))
    t_render = 0.0
    t_wait = 0.0
    pending: Future[None] | None = None
    # two sets of output arrays in turn: chunk k renders into one while the writer thread still
    # reads chunk k-1 from the other (chunk k-2's writing, the set's last user, was waited for),
    # so no chunk pays for fresh pages
    buffers = RenderBuffers(sets=2)
    try:
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="morphgs-writer") as pool:
            for start, clean, corrupted, secs in iter_pair_chunks(
                    scene, corrupted_scene, corruption, cams, chunk=opts.chunk, background=opts.background,
                    out=buffers):
                t_render += secs
                if pending is not None:
                    t0 = time.perf_counter()
                    pending.result()
                    t_wait += time.perf_counter() - t0

                side: Any = clean
                if photos is not None:  # the photos as the clean side, with the clean render's depth
                    side = SimpleNamespace(rgb=photos[start:start + len(clean.rgb)].astype(np.float32) / 255.0,
                                           depth=clean.depth)

                def _write(s: int = start, a: Any = side, b: Any = corrupted) -> None:
                    writer.write(s, "clean", a)
                    writer.write(s, "corrupted", b)

                pending = pool.submit(_write)
            if pending is not None:
                t0 = time.perf_counter()
                pending.result()
                t_wait += time.perf_counter() - t0
        writer.close()
        _write_json(tmp / "cameras.json", cams.to_dict())
        final = out_dir / job.rel_dir
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():  # left by a run killed after its rename, before its manifest line
            shutil.rmtree(final)
        os.rename(tmp, final)
    except BaseException:
        writer.close()
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    rel = job.rel_dir
    video = opts.video
    paths = {"dir": rel, "cameras": f"{rel}/cameras.json",
             "clean": f"{rel}/clean.mp4" if video else f"{rel}/clean",
             "corrupted": f"{rel}/corrupted.mp4" if video else f"{rel}/corrupted"}
    if opts.depth:
        paths.update({"clean_depth": f"{rel}/clean", "corrupted_depth": f"{rel}/corrupted"})
    total = time.perf_counter() - t_start + load_seconds
    extra: dict[str, Any] = {"fit": fit_info} if fit_info is not None else {}
    up = job_up(job, scene, recorded, opts.trajectory)
    if up is not None:  # an orbit: the world up it turned around, and the rule that gave it
        extra["up_rule"] = up_rule(job, recorded is not None, opts.trajectory)
    if photos is not None:
        extra["clean_source"] = "photos"
    drawn = corruption.strength(job.seed)
    if drawn is not None:  # the strength this pair drew (from a strength distribution or fixed)
        extra["strength"] = drawn
    return {
        "schema": 1,
        "pair_id": job.pair_id,
        "scene": job.source.id,
        "scene_source": job.source.describe(),
        "split": job.split,
        "pair_index": job.index,
        "config_name": job.config.label,
        "config": job.config.as_dict(),
        "seed": job.seed,
        "frames": len(cams),
        "resolution": [job.width, job.height],
        "depth": opts.depth,
        "video": video,
        "background": list(opts.background),
        "up": up,
        "paths": paths,
        "timings": {"load": round(load_seconds, 4), "perturb": round(t_perturb, 4),
                    "render": round(t_render, 4), "write_wait": round(t_wait, 4), "total": round(total, 4),
                    # the corrupted side without any fit: making it (perturbing, or loading the
                    # cached fit) and half the render pass, which renders both scenes at once
                    "corrupted": round(max(t_perturb - fitting, 0.0) + t_render / 2, 4),
                    # the whole fit it comes from (shared by its pairs; `morphgs.curation.costs`)
                    "fit": None if fit_info is None else fit_info.get("seconds")},
        "morphgs_version": morphgs.__version__,
        **extra,
    }
