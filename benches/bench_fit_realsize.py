"""Steps/s of `morphgs fit` at 960x540 (DL3DV's images_4 size) with the pinned defaults, and the
Gaussian count over time (docs/fit.md, "Speed at real sizes").

    python benches/bench_fit_realsize.py [--steps 700] [--views 24]

The capture: the synthetic room (300k Gaussians) rendered from an orbit (tests/fit_helpers.
make_dataset), fitted from 100k of its centres as points. Prints one JSON line per 100 steps
(steps/s from the loop's own per-step timings, Gaussians at the end) and a summary line.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def main() -> None:
    from fit_helpers import make_dataset
    from morphgs import _core
    from morphgs.fit import FitConfig, fit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=700)
    ap.add_argument("--views", type=int, default=24)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        root, _, _ = make_dataset(Path(tmp) / "ds", views=args.views, size=(960, 540), gaussians=300_000,
                                  points=100_000)
        print(json.dumps({"dataset_s": round(time.perf_counter() - t, 1)}), flush=True)
        cfg = FitConfig().to_dict()
        cfg["steps"] = args.steps
        cfg["output"] = {"eval_every": 0, "checkpoint_every": 100_000, "preview_every": 0, "progress_every": 0.0,
                         "lpips": "off"}
        run = Path(tmp) / "run"
        r = fit(root, run, config=cfg, init="points", progress=False)
        with open(run / "loss.csv", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        for a in range(0, len(rows), 100):
            chunk = rows[a:a + 100]
            s = sum(float(x["seconds"]) for x in chunk)
            print(json.dumps({"steps": f"{chunk[0]['step']}-{chunk[-1]['step']}",
                              "gaussians_end": int(chunk[-1]["gaussians"]),
                              "steps_per_s": round(len(chunk) / s, 3)}), flush=True)
        print(json.dumps({"threads": _core.num_threads(), "steps_per_second": r.steps_per_second,
                          "gaussians": r.gaussians, "heldout_psnr": r.heldout_psnr, "wall_s": round(r.seconds, 1)}))


if __name__ == "__main__":
    main()
