"""PLY load/save, side by side: morphgs vs plyfile (+ the numpy conversion to the same arrays) vs a
bare ``np.fromfile`` of the same bytes.

    python benches/bench_ply.py            # 1,000,000 Gaussians, SH degree 3
    python benches/bench_ply.py --quick    # 20,000 Gaussians, two runs (smoke check)

The file is written once from ``morphgs.synthetic`` and read once before timing, so every reader
sees it in the page cache. Times are the best of several runs. Peak memory of ``morphgs.load`` is
measured in a fresh subprocess: the peak resident size (VmHWM, reset just before the load)
minus the resident size right before it,
compared with the bytes of the scene's arrays.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import morphgs
from morphgs import synthetic

_PEAK_SNIPPET = r"""
import json, sys
import numpy as np
kind, path = sys.argv[1], sys.argv[2]
def status_kib(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise RuntimeError(key)
if kind == "morphgs":
    import morphgs
    def run():
        s = morphgs.load(path)
        return sum(a.nbytes for a in (s.means, s.quats, s.log_scales, s.opacity_logits, s.sh0, s.sh_rest))
elif kind == "plyfile":
    sys.path.insert(0, sys.argv[3])
    from bench_ply import plyfile_to_arrays
    def run():
        return sum(a.nbytes for a in plyfile_to_arrays(path))
else:
    def run():
        return np.fromfile(path, dtype=np.uint8).nbytes
try:  # reset the high-water mark to the current RSS (Linux >= 4.0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
except OSError:
    pass
before = status_kib("VmRSS")
nbytes = run()
print(json.dumps({"before_kib": before, "peak_kib": status_kib("VmHWM"), "array_bytes": nbytes}))
"""


def plyfile_to_arrays(path: str | Path) -> tuple[np.ndarray, ...]:
    """The peer path: plyfile, then numpy to the arrays morphgs returns (float32, quats normalised,
    f_rest transposed to (N,K,3))."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    names = v.dtype.names or ()

    def cols(keys: list[str]) -> np.ndarray:
        return np.stack([np.asarray(v[k], dtype=np.float32) for k in keys], axis=1)

    means = cols(["x", "y", "z"])
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    log_scales = cols(["scale_0", "scale_1", "scale_2"])
    opacity = np.asarray(v["opacity"], dtype=np.float32)
    sh0 = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    n_rest = sum(1 for k in names if k.startswith("f_rest_"))
    k = n_rest // 3
    rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(len(v), 3, k)
    sh_rest = np.ascontiguousarray(rest.transpose(0, 2, 1))
    return means, quats, log_scales, opacity, sh0, sh_rest


def best_of(fn: Callable[[], Any], runs: int) -> float:
    best = float("inf")
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
        del out
    return best


def peak(kind: str, path: Path) -> dict[str, int]:
    here = str(Path(__file__).resolve().parent)
    out = subprocess.run([sys.executable, "-c", _PEAK_SNIPPET, kind, str(path), here],
                         check=True, capture_output=True, text=True, env=os.environ.copy())
    return json.loads(out.stdout)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20k Gaussians, two runs (smoke check)")
    ap.add_argument("--gaussians", type=int, default=1_000_000)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--dir", type=Path, default=None, help="where to write the test file")
    args = ap.parse_args()
    n = 20_000 if args.quick else args.gaussians
    runs = 2 if args.quick else args.runs

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = Path(tmp) / "bench.ply"
        scene = synthetic.scene(n, sh_degree=3, seed=0)
        morphgs.save_ply(scene, path)
        size = path.stat().st_size
        array_bytes = sum(a.nbytes for a in (scene.means, scene.quats, scene.log_scales,
                                              scene.opacity_logits, scene.sh0, scene.sh_rest))
        del scene
        np.fromfile(path, dtype=np.uint8)  # warm the page cache

        # check the peer path computes what morphgs does before timing it
        ours = morphgs.load(path)
        theirs = plyfile_to_arrays(path)
        for name, a, b in zip(["means", "quats", "log_scales", "opacity", "sh0", "sh_rest"],
                              [ours.means, ours.quats, ours.log_scales, ours.opacity_logits,
                               ours.sh0, ours.sh_rest], theirs):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7, err_msg=name)
        del ours, theirs

        t_morphgs = best_of(lambda: morphgs.load(path), runs)
        t_plyfile = best_of(lambda: plyfile_to_arrays(path), max(1, min(runs, 3)))
        t_fromfile = best_of(lambda: np.fromfile(path, dtype=np.uint8), runs)
        loaded = morphgs.load(path)
        out = Path(tmp) / "saved.ply"
        t_save = best_of(lambda: morphgs.save_ply(loaded, out), max(1, min(runs, 3)))
        del loaded
        mem = {k: peak(k, path) for k in ("morphgs", "plyfile", "fromfile")}

    mb = size / 1e6
    print(f"PLY benchmark: {n:,} Gaussians, SH degree 3, {mb:.1f} MB file, "
          f"{morphgs.num_threads()} morphgs threads, {os.cpu_count()} CPUs, best of {runs}")
    print(f"{'reader':<34}{'time (ms)':>10}{'GB/s':>8}{'peak RSS (MB)':>15}{'x arrays':>10}")

    def row(label: str, t: float, kind: str | None) -> None:
        extra = ""
        if kind:
            d = (mem[kind]["peak_kib"] - mem[kind]["before_kib"]) * 1024
            extra = f"{d / 1e6:>15.1f}{d / array_bytes:>10.2f}"
        print(f"{label:<34}{t * 1e3:>10.1f}{size / t / 1e9:>8.2f}{extra}")

    row("morphgs.load", t_morphgs, "morphgs")
    row("plyfile + numpy conversion", t_plyfile, "plyfile")
    row("np.fromfile (bare read)", t_fromfile, "fromfile")
    row("morphgs.save_ply (incl. fsync)", t_save, None)
    peak_ratio = (mem["morphgs"]["peak_kib"] - mem["morphgs"]["before_kib"]) * 1024 / array_bytes
    print(f"scene arrays: {array_bytes / 1e6:.1f} MB")
    print(f"speed-up over plyfile: {t_plyfile / t_morphgs:.2f}x (target >= 3x)")
    print(f"morphgs.load / np.fromfile: {t_morphgs / t_fromfile:.2f}x (target <= 1.5x)")
    print(f"peak memory / array bytes: {peak_ratio:.2f}x (target <= 1.5x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
