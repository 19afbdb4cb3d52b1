"""Severity (median per-frame PSNR of perturbed vs clean renders) against strength, on the
built-in sample scenes: the strength parameterisation (`FAMILY~S`) next to `morphological@K`
(`PerturbConfig.scaled`). Prints the markdown table of docs/perturbation.md.

    python benches/severity_strength.py [--gaussians 100000] [--frames 16] [--size 192x128]
"""

from __future__ import annotations

import argparse

import numpy as np

import morphgs
from morphgs import synthetic, trajectory
from morphgs.rendering import render_many
from morphgs.strength import FAMILIES, Strength

GRID = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
K_GRID = (0.5, 1.0, 1.5, 1.9, 2.0, 4.0)


def _psnr(a: object, b: object) -> float:
    mse = ((a.rgb.astype(np.float64) - b.rgb) ** 2).mean(axis=(1, 2, 3))  # type: ignore[attr-defined]
    return float(np.median(10 * np.log10(1.0 / np.maximum(mse, 1e-12))))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--size", default="192x128")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.split("x"))
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], a.frames, start_degrees=90.0,
                            arc_degrees=60.0, fov_y_degrees=50.0, resolution=(w, h))
    print("| scene | config | " + " | ".join(f"s={s:g}" for s in GRID) + " |")
    print("|---|---|" + "---|" * len(GRID))
    for sample in (0, 1):
        scene = synthetic.scene(n_gaussians=a.gaussians, seed=sample)
        (clean,) = render_many([scene], cams)
        for fam in FAMILIES:
            row = [_psnr(render_many([Strength(fam, s).apply(scene, seed=a.seed, cameras=cams)], cams)[0], clean)
                   for s in GRID]
            print(f"| sample-{sample} | `{fam}~s` | " + " | ".join(f"{v:.1f}" for v in row) + " |")
        row2 = []
        for k in K_GRID:
            p = morphgs.perturb(scene, morphgs.PerturbConfig.preset("morphological").scaled(k), seed=a.seed)
            row2.append(f"{_psnr(render_many([p], cams)[0], clean):.1f}" if len(p) else "empty")
        print(f"| sample-{sample} | `morphological@k`, k = {', '.join(f'{k:g}' for k in K_GRID)} | "
              + " | ".join(row2) + " |")


if __name__ == "__main__":
    main()
