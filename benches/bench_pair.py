"""End-to-end cost of one training pair through `morphgs curate`.

One 49-frame 832x480 pair (clean + morphological, RGB PNG and depth EXR) of a 1M-Gaussian
synthetic scene: load the PLY, perturb, render both sequences (chunks of 8 frames, both scenes
per pass) while a writer thread encodes the previous chunk, rename into place, append the
manifest. Reports wall seconds and the share of it spent rendering (targets: <= 20 s, >= 80 %).

    python benches/bench_pair.py            # full size (about a minute on 2 cores)
    python benches/bench_pair.py --quick    # smoke check
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import morphgs
from morphgs import synthetic, trajectory


def _camera_path(cams: morphgs.Cameras, fov: float, path: Path) -> None:
    """Write the cameras as a nerfstudio camera_path.json (OpenGL c2w, row-major)."""
    import numpy as np

    gl = cams.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])
    path.write_text(json.dumps({
        "camera_type": "perspective", "render_width": cams.width, "render_height": cams.height,
        "camera_path": [{"camera_to_world": m.reshape(-1).tolist(), "fov": fov} for m in gl]}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny size (smoke check)")
    ap.add_argument("--gaussians", type=int, default=1_000_000)
    ap.add_argument("--frames", type=int, default=49)
    ap.add_argument("--size", default="832x480")
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2, help="MORPHGS_NUM_THREADS (2 = the target machine)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the render-only reference pass")
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.frames, args.size = 20_000, 8, "208x120"
    os.environ["MORPHGS_NUM_THREADS"] = str(args.threads)
    w, h = (int(v) for v in args.size.split("x"))

    work = Path(tempfile.mkdtemp(prefix="morphgs-bench-pair-"))
    try:
        t0 = time.perf_counter()
        scene = synthetic.scene(n_gaussians=args.gaussians, sh_degree=3, seed=0)
        t_gen = time.perf_counter() - t0
        folder = work / "scene"
        folder.mkdir()
        t0 = time.perf_counter()
        morphgs.save_ply(scene, folder / "scene.ply")
        t_save = time.perf_counter() - t0
        o = synthetic.suggested_orbit()
        fov = 50.0
        cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], args.frames, start_degrees=135,
                                arc_degrees=90, fov_y_degrees=fov, resolution=(w, h))
        _camera_path(cams, fov, folder / "camera_path.json")

        out = work / "out"
        t0, c0 = time.perf_counter(), time.process_time()
        summary = morphgs.curate([folder], out, configs=["morphological"], pairs_per_scene=1,
                                 frames=args.frames, resolution=(w, h), depth=True, chunk=args.chunk,
                                 progress=False)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        assert summary.ok and summary.done == 1, summary.text()
        rec = summary.records[0]
        tm = rec["timings"]
        n_png = len(list((out / rec["paths"]["dir"]).rglob("*.png")))
        n_exr = len(list((out / rec["paths"]["dir"]).rglob("*.exr")))
        size_mb = sum(p.stat().st_size for p in (out / rec["paths"]["dir"]).rglob("*") if p.is_file()) / 1e6

        base = None
        if not args.no_baseline:
            loaded = morphgs.load(folder / "scene.ply")
            pert = morphgs.perturb(loaded, "morphological", seed=rec["seed"])
            t0 = time.perf_counter()
            morphgs.render_many([loaded, pert], cams)
            base = time.perf_counter() - t0

        print(f"bench_pair: {args.gaussians:,} Gaussians, {args.frames} frames {w}x{h}, clean + morphological, "
              f"PNG + depth EXR, {morphgs.num_threads()} threads, chunk {args.chunk}")
        print(f"  (setup, not timed: synthetic scene {t_gen:.2f} s, save PLY {t_save:.2f} s)")
        print(f"  {'stage':<34}{'seconds':>10}{'share':>9}")
        rows = [("load PLY", tm["load"]), ("perturb", tm["perturb"]),
                ("render (2 scenes, all chunks)", tm["render"]),
                ("render waiting for the writer", tm["write_wait"]),
                ("other (paths, rename, manifest)", wall - tm["load"] - tm["perturb"] - tm["render"] - tm["write_wait"])]
        for name, s in rows:
            print(f"  {name:<34}{s:>10.3f}{100 * s / wall:>8.1f}%")
        print(f"  {'end to end (curate call)':<34}{wall:>10.3f}{100.0:>8.1f}%")
        print(f"  render share of end to end: {100 * tm['render'] / wall:.1f}%  (target >= 80%)")
        print(f"  end to end: {wall:.2f} s  (target <= 20 s at full size)")
        print(f"  process CPU of the curate call (all threads): {cpu:.2f} s")
        print(f"  files: {n_png} PNG + {n_exr} EXR, {size_mb:.1f} MB")
        if base is not None:
            print(f"  reference: render_many([clean, perturbed]) of all {args.frames} frames in one call, "
                  f"no writing: {base:.3f} s")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
