"""The sparse-view corruption families (docs/artifacts.md) on a built-in room: per family, the
PSNR of the corrupted render at the virtual training views and between them, and the time of
`Strength.apply` (which renders the training views it needs). Reports; asserts nothing.

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
from morphgs.strength import Strength


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
    print(f"{'family':<15} {'Gaussians':>9} {'PSNR train':>11} {'PSNR between':>13} {'apply ms':>9}")
    for fam in ("depth", "view_color", "needles", "holes", "dilate", "floaters", "sparse-like", "morphological"):
        st = Strength(fam, a.strength, train_every=a.every)
        t0 = time.perf_counter()
        out = st.apply(scene, seed=1, cameras=cams)
        ms = (time.perf_counter() - t0) * 1000
        bad = morphgs.render(out, cams).to_uint8().astype(np.float64)
        psnr = 10 * np.log10(255.0**2 / np.maximum(((bad - clean) ** 2).mean(axis=(1, 2, 3)), 1e-12))
        print(f"{fam:<15} {len(out):>9} {psnr[train].mean():>11.2f} {np.delete(psnr, train).mean():>13.2f} "
              f"{ms:>9.0f}")


if __name__ == "__main__":
    main()
