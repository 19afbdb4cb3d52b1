"""`morphgs info FILE`: what a scene file holds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

import morphgs


def register(sub: Any) -> None:
    p = sub.add_parser("info", help="summarise a scene file (count, SH degree, bounds, statistics)")
    p.add_argument("file", help="a scene file, or a folder curate reads (a fit/INRIA run folder: its last iteration)")
    p.add_argument("--json", action="store_true", help="print machine-readable JSON")
    p.set_defaults(func=run)


def _stats(a: np.ndarray) -> dict[str, float]:
    if a.size == 0:
        return {}
    q = np.percentile(a, [1, 50, 99])
    return {"min": float(a.min()), "p01": float(q[0]), "median": float(q[1]),
            "p99": float(q[2]), "max": float(a.max()), "mean": float(a.mean())}


def summary(scene: morphgs.GaussianScene) -> dict[str, Any]:
    lo, hi = scene.bounds()
    return {
        "gaussians": len(scene),
        "sh_degree": scene.sh_degree,
        "bounds_min": [float(v) for v in lo],
        "bounds_max": [float(v) for v in hi],
        "scale": _stats(scene.scales.max(axis=1)) if len(scene) else {},
        "opacity": _stats(scene.opacities),
        "extras": sorted(scene.extras),
    }


def run(args: argparse.Namespace) -> int:
    path = Path(args.file)
    if path.is_dir():
        from morphgs.curation.sources import scene_file_in

        path = scene_file_in(path)
    scene = morphgs.load(path)
    s = summary(scene)
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"{path}")
    print(f"  gaussians : {s['gaussians']:,}")
    print(f"  sh degree : {s['sh_degree']}")
    print("  bounds    : min [{}]  max [{}]".format(
        ", ".join(f"{v:.3f}" for v in s["bounds_min"]), ", ".join(f"{v:.3f}" for v in s["bounds_max"])))
    for key in ("scale", "opacity"):
        st = s[key]
        if st:
            label = "max scale" if key == "scale" else "opacity"
            print(f"  {label:<10}: min {st['min']:.4g}  median {st['median']:.4g}  "
                  f"p99 {st['p99']:.4g}  max {st['max']:.4g}")
    if s["extras"]:
        print(f"  extras    : {', '.join(s['extras'])}")
    return 0
