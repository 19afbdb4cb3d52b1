"""Held-out PSNR of `morphgs fit` on a forward-facing (LLFF-style) capture of the synthetic room
from three initialisations: SfM-like points, `random` (points along the training rays) and `box`
(uniform in the box of the camera centres, the old `random`). docs/fit.md, "Initialisation".

    python benches/bench_fit_init.py [--steps 600] [--layout forward|orbit]

Prints one JSON line per init. The capture: tests/capture_helpers.forward_facing_cameras (a 5x4
grid, 96x72), a 20k-Gaussian room; the "SfM points" are 3000 Gaussian centres seen by the middle
camera. `--layout orbit`: 24 inward views of the room (tests/fit_helpers.make_dataset, 96x72,
20k Gaussians, 3000 centres as points). The config is tests/fit_helpers.small_config with
refinement every 100 steps.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def main() -> None:
    from capture_helpers import forward_facing_cameras, write_transforms
    from fit_helpers import small_config, write_point_ply
    from morphgs import synthetic
    from morphgs.fit import fit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--layout", choices=("forward", "orbit"), default="forward")
    args = ap.parse_args()
    scene = synthetic.scene(20000, sh_degree=1, seed=0)
    cams = forward_facing_cameras((96, 72))
    with tempfile.TemporaryDirectory() as tmp:
        if args.layout == "orbit":
            from fit_helpers import make_dataset

            root, _, _ = make_dataset(Path(tmp) / "orbit", views=24, size=(96, 72), gaussians=20000, points=3000)
        else:
            root = write_transforms(Path(tmp) / "ff", scene, cams)
        mid = cams[7]
        m = np.asarray(scene.means)
        uv = mid.project(m)
        zc = (m @ mid.world_to_camera[:3, :3].T + mid.world_to_camera[:3, 3])[:, 2]
        vis = (zc > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < mid.width) & (uv[:, 1] >= 0) & (uv[:, 1] < mid.height)
        idx = np.random.default_rng(0).choice(np.flatnonzero(vis), size=min(3000, int(vis.sum())), replace=False)
        if args.layout == "forward":
            write_point_ply(root / "points.ply", m[idx], np.clip(np.asarray(scene.colors)[idx], 0, 1))
        cfg = small_config(args.steps, init={"random_points": 5000},
                           output={"eval_every": 0, "checkpoint_every": 100000, "preview_every": 0,
                                   "progress_every": 0.0, "lpips": "off"})
        cfg["default"] = {"refine_start": 100, "refine_every": 100, "reset_every": 3000,
                          "refine_stop": max(args.steps - 100, 0)}
        for init in (f"ply:{root / 'points.ply'}", "random", "box"):
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = fit(root, Path(tmp) / f"run-{init.split(':')[0]}", config=cfg, init=init, progress=False)
            print(json.dumps({"init": init.split(":")[0], "steps": args.steps, "heldout_psnr": round(r.heldout_psnr or 0, 2),
                              "heldout_ssim": round(r.heldout_ssim or 0, 4), "gaussians": r.gaussians,
                              "seconds": round(time.perf_counter() - t, 1)}), flush=True)


if __name__ == "__main__":
    main()
