"""Export time per pair for every `morphgs export` format.

Curates (untimed) a few 49-frame 832x480 pairs with depth from the built-in sample scenes, then
times each export on them: wall seconds per pair, CPU seconds per pair (this process plus its ffmpeg
children), and megabytes written per pair. The MP4 formats are also timed with one clip encoded at a
time (`workers=1`) to show what encoding clips side by side buys.

    python benches/bench_export.py            # 4 pairs, 49 frames 832x480 (a few minutes on 2 cores)
    python benches/bench_export.py --quick    # smoke check: 2 pairs of 9 frames 224x128
    python benches/bench_export.py --cases diffsynth --repeat 3   # some rows, several times
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import morphgs
from morphgs import exports

# (label, format, options)
CASES: list[tuple[str, str, dict[str, Any]]] = [
    ("diffsynth", "diffsynth", {}),
    ("diffsynth, workers=1", "diffsynth", {"workers": 1}),
    ("diffsynth + reference image", "diffsynth", {"reference_frame": 0}),
    ("videox-fun", "videox-fun", {}),
    ("thedenk", "thedenk", {}),
    ("webdataset, no depth", "webdataset", {"depth": False}),
    ("webdataset, no depth, workers=1", "webdataset", {"depth": False, "workers": 1}),
    ("webdataset + float32 depth", "webdataset", {}),
    ("webdataset + float16 depth", "webdataset", {"depth_dtype": "float16"}),
    ("difix (data.json only)", "difix", {}),
]


def _cpu() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny size (smoke check)")
    ap.add_argument("--frames", type=int, default=49)
    ap.add_argument("--size", default="832x480")
    ap.add_argument("--pairs-per-scene", type=int, default=2, help="pairs of each of the 2 built-in scenes")
    ap.add_argument("--threads", type=int, default=2, help="MORPHGS_NUM_THREADS (2 = the target machine)")
    ap.add_argument("--cases", default="", help="only the rows whose label contains this text")
    ap.add_argument("--repeat", type=int, default=1, help="time each row this many times (one line each)")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.size, args.pairs_per_scene = 9, "224x128", 1
    os.environ["MORPHGS_NUM_THREADS"] = str(args.threads)
    w, h = (int(v) for v in args.size.split("x"))

    work = Path(tempfile.mkdtemp(prefix="morphgs-bench-export-"))
    try:
        data = work / "data"
        t0 = time.perf_counter()
        summary = morphgs.curate(out=data, pairs_per_scene=args.pairs_per_scene, frames=args.frames,
                                 resolution=(w, h), depth=True, builtin_gaussians=20_000 if args.quick else 100_000,
                                 progress=False, log=lambda m: None)
        assert summary.ok, summary.text()
        n = summary.done
        print(f"bench_export: {n} pairs of {args.frames} frames {w}x{h} (PNG + depth EXR, curated in "
              f"{time.perf_counter() - t0:.1f} s, not timed), {morphgs.num_threads()} threads, "
              f"{os.cpu_count()} CPUs")
        print(f"  {'format':<34}{'wall s/pair':>12}{'CPU s/pair':>12}{'MB/pair':>10}")
        for _ in range(args.repeat):
            for label, fmt, opts in CASES:
                if args.cases not in label:
                    continue
                out = work / "out"
                c0, t0 = _cpu(), time.perf_counter()
                exports.export(fmt, data, out, **opts, progress=False)
                wall, cpu = time.perf_counter() - t0, _cpu() - c0
                print(f"  {label:<34}{wall / n:>12.2f}{cpu / n:>12.2f}{_mb(out) / n:>10.1f}", flush=True)
                shutil.rmtree(out)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
