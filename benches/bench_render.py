"""Rasterizer benchmark: garden scene (gsplat's profiling setup) and the grid-5 scene.

Prints per-frame wall and CPU times, stage times, the blend's evaluations (the lanes of the
kernel's work units: 4x4-pixel blocks for AVX-512, 8-pixel half rows for AVX2, 16-pixel rows for
the plain kernel) beside the useful ones
(alpha >= 1/255 before the pixel stops: the limit a lossless blend could reach) and their ratio,
blend throughput (Gaussian-pixel evaluations per second), the 1 -> N thread speed-up and the
ratio against gsplat's torch reference on CPU (its projection plus the float64 reference blend of tests/render_reference.py).

    python benches/bench_render.py            # full run (< 3 minutes on 2 cores)
    python benches/bench_render.py --quick    # tiny smoke run

The garden frame is also rendered with the lower blend kernels (MORPHGS_SIMD=avx2, scalar).

Thread counts are fixed per process (RAYON_NUM_THREADS), so each configuration runs in a
subprocess.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
FIXTURES = Path(os.environ.get("MORPHGS_FIXTURES", REPO / "tests" / "fixtures"))


def _worker(args: argparse.Namespace) -> None:
    import morphgs
    from render_reference import garden

    scene, cams = garden(FIXTURES, grid=args.grid)
    cam = cams[0]
    if (args.width, args.height) != (cam.width, cam.height):
        cam = cams.resized(args.width, args.height)[0]
    morphgs.render(scene, cam)  # warm-up (page faults, pool start)
    walls, cpus, stats = [], [], []
    for _ in range(args.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        r = morphgs.render(scene, cam)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        stats.append(r.stats)
    best = int(np.argmin(walls))
    # one more render, untimed, counting the evaluations that can change a pixel (alpha >=
    # 1/255 before the pixel stops): counting slows the blend, so the timed renders do not
    os.environ["MORPHGS_COUNT_USEFUL"] = "1"
    useful = morphgs.render(scene, cam).stats["useful_evaluations"]
    del os.environ["MORPHGS_COUNT_USEFUL"]
    print(json.dumps({"n": len(scene), "wall": walls, "cpu": cpus, "stats": stats[best],
                      "useful": useful}))


def run(grid: int, width: int, height: int, threads: int, repeat: int, simd: str = "auto") -> dict:
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads), MORPHGS_SIMD=simd)
    env.pop("MORPHGS_NUM_THREADS", None)
    out = subprocess.run(
        [sys.executable, __file__, "--worker", "--grid", str(grid), "--width", str(width),
         "--height", str(height), "--repeat", str(repeat)],
        env=env, capture_output=True, text=True, check=True, timeout=600,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def row(label: str, threads: int, res: dict) -> str:
    s = res["stats"]
    w = np.array(res["wall"]) * 1e3
    rate = s["evaluations"] / s["blend_s"] / 1e9
    c = np.array(res["cpu"]) * 1e3
    useful = res["useful"]
    return (f"{label:<26} {threads:>3} {np.median(w):9.1f} {w.min():9.1f} {np.median(c):7.1f} "
            f"{s['project_s']*1e3:7.1f} {s['sort_s']*1e3:6.1f} {s['bin_s']*1e3:6.1f} "
            f"{s['blend_s']*1e3:7.1f} {s['evaluations']/1e6:8.1f} {useful/1e6:8.1f} "
            f"{100*useful/max(s['evaluations'], 1):5.1f} {rate:6.2f}")


def reference_ratio(quick: bool) -> None:
    import morphgs
    from render_reference import garden, gsplat_project, reference_blend

    scene, cams = garden(FIXTURES)
    cam = cams[0]
    w, h = (64, 48) if quick else (176, 112)
    crop = morphgs.Camera(cam.fx, cam.fy, cam.cx - 232, cam.cy - 150, w, h, cam.world_to_camera)
    gsplat_project(scene.subset(np.arange(10)), crop)  # import torch/gsplat outside the timing
    t0 = time.perf_counter()
    ref = gsplat_project(scene, crop)
    t1 = time.perf_counter()
    reference_blend(ref, crop.width, crop.height)
    t2 = time.perf_counter()
    morphgs.render(scene, crop)
    ours = []
    for _ in range(5):
        t = time.perf_counter()
        morphgs.render(scene, crop)
        ours.append(time.perf_counter() - t)
    mine = min(ours)
    print(f"\ngsplat torch reference on CPU ({w}x{h} window of garden camera 0, {len(scene)} Gaussians):")
    print(f"  gsplat _torch_impl projection+SH {1e3*(t1-t0):9.1f} ms  (torch threads: 1)")
    print(f"  float64 reference blend          {1e3*(t2-t1):9.1f} ms")
    print(f"  morphgs render                   {1e3*mine:9.1f} ms  -> {(t2-t0)/mine:,.0f}x faster")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke check)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--grid", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--width", type=int, default=648, help=argparse.SUPPRESS)
    ap.add_argument("--height", type=int, default=420, help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(args)
        return

    import morphgs

    ncpu = os.cpu_count() or 1
    rep = 2 if args.quick else 7
    configs = [("garden 648x420", 1, 648, 420)]
    if args.quick:
        configs = [("garden 162x105", 1, 162, 105)]
    else:
        configs.append(("garden grid-5 1920x1080", 5, 1920, 1080))
    print(f"morphgs {morphgs.__version__}; {ncpu} CPUs; times per frame; cpu = median process "
          f"CPU ms; stage columns in ms from the best run; evals = lanes of the kernel's work "
          f"units evaluated (AVX-512: 4x4-pixel blocks, AVX2: 8-pixel half rows, plain: "
          f"16-pixel rows); useful = evaluations with alpha >= "
          f"1/255 on a pixel not yet stopped (the ones that can change it), eff% = useful / "
          f"evals (the blend's efficiency); G/s = blend evaluations per blend second")
    print(f"{'scene':<26} {'thr':>3} {'median ms':>9} {'best ms':>9} {'cpu ms':>7} {'proj':>7} "
          f"{'sort':>6} {'bin':>6} {'blend':>7} {'evals M':>8} {'useful M':>8} {'eff%':>5} "
          f"{'G/s':>6}")
    for label, grid, w, h in configs:
        results = {}
        for threads in sorted({1, ncpu}):
            res = run(grid, w, h, threads, rep if grid == 1 else max(2, rep // 3))
            results[threads] = res
            print(row(label, threads, res), flush=True)
        if ncpu > 1:
            t1 = min(results[1]["wall"])
            tn = min(results[ncpu]["wall"])
            print(f"{'':<26} speed-up 1 -> {ncpu} threads: {t1 / tn:.2f}x "
                  f"(Gaussians: {results[1]['n']:,}, visible: {results[1]['stats']['visible']:,}, "
                  f"kernel: {results[1]['stats']['simd']})")
        if grid == 1:
            # the lower kernels on the same frame (MORPHGS_SIMD picks them)
            for simd in ("avx2", "scalar"):
                res = run(grid, w, h, ncpu, rep, simd)
                if res["stats"]["simd"] != results[ncpu]["stats"]["simd"]:
                    print(row(f"  {res['stats']['simd']} kernel", ncpu, res), flush=True)
    reference_ratio(args.quick)


if __name__ == "__main__":
    main()
