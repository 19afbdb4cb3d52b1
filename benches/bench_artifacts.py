"""The sparse-view corruption families (docs/artifacts.md) on a built-in room: per family, the
PSNR of the corrupted render at the virtual training views and between them, the flicker (RMS
frame-to-frame change of the error, 8-bit units: popping's signature), the time of
`Strength.apply` (which renders the training views it needs) and of the corrupted render along
the orbit (popping renders each frame with its own visibility). Reports; asserts nothing.

    python benches/bench_artifacts.py [--gaussians 30000] [--size 160x120] [--views 32] [--every 8]
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import time

import numpy as np

import morphgs
from morphgs import synthetic, trajectory
from morphgs.strength import BASE, FAMILIES, Strength

FAMS = ("depth", "view_color", "needles", "holes", "dilate", "floaters", "popping", "sparse-like",
        "sparse-like+popping", "morphological")


def config(fam: str, strength: float, every: int) -> Strength:
    """A family, or "sparse-like+popping": sparse-like's ops and popping at their bases."""
    if fam == "sparse-like+popping":
        ops = {k: BASE[k] for k in (*FAMILIES["sparse-like"], "popping")}
        return Strength("sparse-like", strength, ops, train_every=every)
    return Strength(fam, strength, train_every=every)


def cpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=30000)
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--views", type=int, default=32)
    ap.add_argument("--every", type=int, default=8)
    ap.add_argument("--strength", type=float, default=1.0)
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.split("x"))
    scene = synthetic.scene(a.gaussians, sh_degree=3, seed=0)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], a.views, start_degrees=0.0, arc_degrees=300,
                            fov_y_degrees=50.0, resolution=(w, h))
    clean = morphgs.render(scene, cams).to_uint8().astype(np.float64)
    train = np.arange(0, a.views, a.every)
    print(f"{cpu()}, {morphgs.num_threads()} threads; {a.gaussians} Gaussians, {a.views} views at {w}x{h}, "
          f"training views every {a.every}th, strength {a.strength}")
    print(f"{'family':<20} {'Gaussians':>9} {'PSNR train':>11} {'PSNR between':>13} {'flicker':>8} {'apply ms':>9} "
          f"{'render ms':>10}")
    for fam in FAMS:
        st = config(fam, a.strength, a.every)
        t0 = time.perf_counter()
        out = st.apply(scene, seed=1, cameras=cams)
        ms = (time.perf_counter() - t0) * 1000
        t0 = time.perf_counter()
        frames = morphgs.render(out, cams)
        render_ms = (time.perf_counter() - t0) * 1000
        bad = frames.to_uint8().astype(np.float64)
        psnr = 10 * np.log10(255.0**2 / np.maximum(((bad - clean) ** 2).mean(axis=(1, 2, 3)), 1e-12))
        err = bad - clean
        flicker = np.sqrt(np.mean((err[1:] - err[:-1]) ** 2))
        print(f"{fam:<20} {len(out):>9} {psnr[train].mean():>11.2f} {np.delete(psnr, train).mean():>13.2f} "
              f"{flicker:>8.2f} {ms:>9.0f} {render_ms:>10.0f}")


if __name__ == "__main__":
    main()
