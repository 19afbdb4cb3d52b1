"""The fit-bytes check of a speed change: fit the garden dataset of `bench_fit.py` for N steps and
print the sha256 of the written PLY, for this checkout's build and (with --baseline DIR) for an
older build's `morphgs` package, at each thread count and kernel level asked for. A change that
keeps the fit's bytes prints one hash per kernel level.

    python benches/fit_bytes.py                                   # 150 steps, 1 and 2 threads
    python benches/fit_bytes.py --baseline /tmp/old --simd native,avx2,scalar

Each fit runs in its own process (the thread count and kernel level are fixed per process). The
dataset (24 views of gsplat's garden profiling scene at 648x420 and the garden points) is built
once in a temporary folder.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benches"))
sys.path.insert(0, str(REPO / "tests"))


def fit_hash(dataset: Path, out: Path, steps: int) -> str:
    """Fit `dataset` for `steps` steps into `out`; the sha256 of the last PLY it wrote."""
    from morphgs.fit import FitConfig, fit

    cfg = FitConfig.from_dict({"steps": steps})
    fit(dataset, out, config=cfg, views="all", holdout="every:8", init="auto", progress=False)
    ply = max(out.rglob("point_cloud.ply"), key=lambda p: p.stat().st_mtime)
    return hashlib.sha256(ply.read_bytes()).hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument(
        "--simd", default="native", help="comma-separated MORPHGS_SIMD levels (native = unset)"
    )
    ap.add_argument("--baseline", type=Path, help="a folder holding an older build's morphgs")
    ap.add_argument("--worker", nargs=3, metavar=("DATASET", "OUT", "STEPS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        d, o, n = args.worker
        print(fit_hash(Path(d), Path(o), int(n)))
        return
    from bench_fit import garden_dataset

    builds = [("this", None)] + ([("baseline", args.baseline)] if args.baseline else [])
    with tempfile.TemporaryDirectory(prefix="morphgs-fitbytes-") as tmp:
        ds = Path(tmp) / "garden"
        garden_dataset(ds, 24)
        for simd in args.simd.split(","):
            seen = set()
            for threads in args.threads.split(","):
                for name, path in builds:
                    env = dict(os.environ, MORPHGS_NUM_THREADS=threads)
                    env.pop("MORPHGS_SIMD", None)
                    if simd != "native":
                        env["MORPHGS_SIMD"] = simd
                    if path is not None:
                        env["PYTHONPATH"] = str(path)
                    out = Path(tmp) / f"run-{name}-{simd}-{threads}"
                    cmd = [sys.executable, __file__, "--worker", str(ds), str(out), str(args.steps)]
                    h = subprocess.run(
                        cmd, env=env, check=True, capture_output=True, text=True
                    ).stdout.split()[-1]
                    seen.add(h)
                    print(f"simd={simd:7s} threads={threads:2s} {name:8s} {h[:16]}", flush=True)
            print(f"simd={simd}: {'same bytes' if len(seen) == 1 else 'BYTES DIFFER'}")


if __name__ == "__main__":
    main()
