"""Backward-pass benchmark: forward (with saved state) + backward of the garden frame and of the
grid-5 scene at 1920x1080, and the torch op against gsplat's torch reference with autograd.

Prints per-step wall times (median and best), each stage's best time over the steps (on a
shared machine the minimum is the least disturbed figure), the blend-backward rate (Gaussian-
pixel evaluations per second), the backward / forward ratio of the best times, peak memory (the
worker process's maximum resident set, scene included) and the slot memory of the backward;
then the ratio of `morphgs.torch.rasterization` forward+backward to gsplat's `_torch_impl`
projection + SH with a dense torch blend (float32, autograd) on a window of garden camera 0.

    python benches/bench_backward.py            # full run (a few minutes on 2 cores)
    python benches/bench_backward.py --quick    # tiny smoke run
    python benches/bench_backward.py --baseline /tmp/old --rounds 5   # A/B against an older build
    python benches/bench_backward.py --baseline /tmp/old --simd avx2  # the same, AVX2 kernels

With --baseline DIR (a folder holding an older build's `morphgs` package), only the A/B runs:
the garden frame's backward at 1 thread (OpenBLAS held to one thread, whose idle threads spin
inside the process otherwise), the older build and this one in alternating processes for
--rounds rounds; per process the median and minimum of the process CPU time of each backward
call and of each stage's wall time, then the median over the rounds of each and new/old.

Thread counts and kernels are fixed per process (RAYON_NUM_THREADS, MORPHGS_SIMD), so each
configuration runs in a subprocess.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
FIXTURES = Path(os.environ.get("MORPHGS_FIXTURES", REPO / "tests" / "fixtures"))


def _worker(args: argparse.Namespace) -> None:
    from backward_reference import Params
    from render_reference import garden

    from morphgs._core import DiffRasterizer

    scene, cams = garden(FIXTURES, grid=args.grid)
    cam = cams[0]
    if (args.width, args.height) != (cam.width, cam.height):
        cam = cams.resized(args.width, args.height)[0]
    p = Params.of(scene)
    del scene
    r = DiffRasterizer()
    n = cam.width * cam.height
    # an L1 loss's image gradient: +-1 / (3 n)
    v_rgb = (np.sign(np.random.default_rng(0).normal(size=(cam.height, cam.width, 3)))
             / (3 * n)).astype(np.float32)
    steps = []
    for i in range(args.repeat + 1):
        t0 = time.perf_counter()
        _, _, _, fs = r.forward(*p.arrays(), cam.world_to_camera, cam.K, cam.width, cam.height)
        t1 = time.perf_counter()
        c1 = time.process_time()
        g = r.backward(*p.arrays(), v_rgb=v_rgb)
        t2 = time.perf_counter()
        c2 = time.process_time()
        if i:  # the first step pays the page faults
            steps.append({"fwd": t1 - t0, "bwd": t2 - t1, "bwd_cpu": c2 - c1, "fs": fs,
                          "bs": g["stats"]})
    # each stage's minimum over the steps
    best = {"fwd": min(s["fwd"] for s in steps), "bwd": min(s["bwd"] for s in steps),
            "fs": {k: (min(s["fs"][k] for s in steps) if k.endswith("_s") else steps[0]["fs"][k])
                   for k in steps[0]["fs"]},
            "bs": {k: (min(s["bs"][k] for s in steps) if k.endswith("_s") else steps[0]["bs"][k])
                   for k in steps[0]["bs"]}}
    print(json.dumps({
        "n": len(p.opacity_logits), "fwd": [s["fwd"] for s in steps],
        "bwd": [s["bwd"] for s in steps], "bwd_cpu": [s["bwd_cpu"] for s in steps],
        "stages": {k: [s["bs"][k] for s in steps] for k in ("blend_s", "reduce_s", "project_s")},
        "best": best,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }))


def run(grid: int, width: int, height: int, threads: int, repeat: int, simd: str = "auto",
        baseline: str | None = None) -> dict:
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads), MORPHGS_SIMD=simd)
    env.pop("MORPHGS_NUM_THREADS", None)
    if baseline is not None:
        env.update(PYTHONPATH=baseline, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, __file__, "--worker", "--grid", str(grid), "--width", str(width),
         "--height", str(height), "--repeat", str(repeat)],
        env=env, capture_output=True, text=True, check=True, timeout=1200,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def row(label: str, threads: int, res: dict) -> str:
    b = res["best"]
    fs, bs = b["fs"], b["bs"]
    step = (np.array(res["fwd"]) + np.array(res["bwd"])) * 1e3
    rate = bs["evaluations"] / bs["blend_s"] / 1e9
    return (f"{label:<24} {threads:>3} {np.median(step):8.1f} {step.min():8.1f} "
            f"{b['fwd']*1e3:7.1f} {b['bwd']*1e3:7.1f} {b['bwd']/b['fwd']:5.2f} "
            f"{bs['blend_s']*1e3:7.1f} {bs['reduce_s']*1e3:6.1f} {bs['project_s']*1e3:6.1f} "
            f"{rate:5.2f} {bs['slot_bytes']/2**20:6.1f} {res['peak_mb']:7.0f}   "
            f"(fwd: proj {fs['project_s']*1e3:.1f} sort {fs['sort_s']*1e3:.1f} "
            f"bin {fs['bin_s']*1e3:.1f} blend {fs['blend_s']*1e3:.1f}; kernel {fs['simd']})")


def ab(baseline: str, rounds: int, quick: bool, simd: str = "auto") -> None:
    """The garden backward at 1 thread, `baseline`'s build and this one alternating, both with
    the kernel `simd` (MORPHGS_SIMD)."""
    w, h = (162, 105) if quick else (648, 420)
    rep = 3 if quick else 20
    print(f"backward A/B, garden {w}x{h}, 1 thread, kernel {simd}, {rounds} rounds of {rep} "
          f"calls per process (load average {os.getloadavg()[0]:.1f}); ms: median / minimum "
          "per process")
    keys = ("bwd_cpu", "blend_s", "reduce_s", "project_s")
    res: dict[str, list[dict]] = {"baseline": [], "this": []}
    evals: dict[str, int] = {}
    for r in range(rounds):
        for build in ("baseline", "this"):
            out = run(1, w, h, 1, rep, simd=simd,
                      baseline=baseline if build == "baseline" else None)
            vals = {k: out["bwd_cpu"] if k == "bwd_cpu" else out["stages"][k] for k in keys}
            d = {k: (float(np.median(v)), float(np.min(v))) for k, v in vals.items()}
            res[build].append(d)
            evals[build] = int(out["best"]["bs"]["evaluations"])
            print(f"{build:>8} {r}  " + "  ".join(
                f"{k} {d[k][0] * 1e3:6.2f}/{d[k][1] * 1e3:6.2f}" for k in keys), flush=True)
    print(f"backward evaluations (the kernel's work units x their pixels): baseline "
          f"{evals['baseline']:,}  this {evals['this']:,}  this/baseline "
          f"{evals['this'] / evals['baseline']:.3f}")
    for i, what in ((0, "median"), (1, "minimum")):
        for k in keys:
            o = float(np.median([d[k][i] for d in res["baseline"]]))
            n = float(np.median([d[k][i] for d in res["this"]]))
            print(f"{what:>8} {k:<10} baseline {o * 1e3:7.2f}  this {n * 1e3:7.2f}  "
                  f"this/baseline {n / o:.3f}")


def torch_ratio(quick: bool) -> None:
    import torch

    import morphgs
    from backward_reference import Params, Reference, Setup, loss_weights
    from morphgs.torch import rasterization
    from render_reference import garden

    torch.set_num_threads(1)
    scene, cams = garden(FIXTURES)
    cam = cams[0]
    w, h = (48, 32) if quick else (176, 112)
    crop = morphgs.Camera(cam.fx, cam.fy, cam.cx - 232, cam.cy - 150, w, h, cam.world_to_camera)
    p = Params.of(scene)
    setup = Setup(crop)
    wts = loss_weights(setup, seed=0)
    w_img = torch.from_numpy(wts["rgb"])[None]

    def ours() -> float:
        x = {"means": torch.tensor(p.means, requires_grad=True),
             "quats": torch.tensor(p.quats, requires_grad=True),
             "scales": torch.exp(torch.tensor(p.log_scales)).requires_grad_(True),
             "opacities": torch.sigmoid(torch.tensor(p.opacity_logits)).requires_grad_(True),
             "colors": torch.tensor(p.sh0)[:, None].requires_grad_(True)}
        vm = torch.tensor(crop.world_to_camera)[None]
        ks = torch.tensor(crop.K)[None]
        t0 = time.perf_counter()
        img, _, _ = rasterization(x["means"], x["quats"], x["scales"], x["opacities"],
                                  x["colors"], vm, ks, w, h, sh_degree=0)
        (img * w_img).sum().backward()
        return time.perf_counter() - t0

    def reference() -> float:
        r = morphgs._core.DiffRasterizer()
        r.forward(*p.arrays(), crop.world_to_camera, crop.K, w, h)
        ref = Reference(p, setup, r, dtype="float32")
        wz = {"rgb": wts["rgb"], "depth": np.zeros_like(wts["depth"]),
              "alpha": np.zeros_like(wts["alpha"])}
        t0 = time.perf_counter()
        ref.grads(p, wz)
        return time.perf_counter() - t0

    ours()
    mine = min(ours() for _ in range(2 if quick else 5))
    theirs = min(reference() for _ in range(1 if quick else 2))
    print(f"\ntorch op vs gsplat's torch reference with autograd on CPU ({w}x{h} window of garden "
          f"camera 0, {len(scene):,} Gaussians, forward + backward, torch threads 1):")
    print(f"  gsplat _torch_impl projection + SH + dense torch blend (float32) "
          f"{theirs*1e3:9.1f} ms")
    print(f"  morphgs.torch.rasterization                                      "
          f"{mine*1e3:9.1f} ms  -> {theirs / mine:,.0f}x faster")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke check)")
    ap.add_argument("--baseline", help="folder holding an older build's morphgs package: run "
                    "only the alternating backward A/B against it")
    ap.add_argument("--rounds", type=int, default=5, help="A/B rounds (with --baseline)")
    ap.add_argument("--simd", default="auto", choices=("auto", "avx512", "avx2", "scalar"),
                    help="the kernel of both builds in the A/B (MORPHGS_SIMD; with --baseline)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--grid", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--width", type=int, default=648, help=argparse.SUPPRESS)
    ap.add_argument("--height", type=int, default=420, help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(args)
        return
    if args.baseline:
        ab(args.baseline, args.rounds, args.quick, args.simd)
        return

    import morphgs

    ncpu = os.cpu_count() or 1
    rep = 2 if args.quick else 30
    print(f"morphgs {morphgs.__version__}; {ncpu} CPUs; load average {os.getloadavg()[0]:.1f}; one "
          f"step = forward + backward (all parameter gradients and densification statistics); "
          f"times in ms; fwd, bwd and stages: best over the steps; G/s = blend-backward "
          f"evaluations per second; peak = worker max RSS")
    print(f"{'scene':<24} {'thr':>3} {'med step':>8} {'best':>8} {'fwd':>7} {'bwd':>7} "
          f"{'ratio':>5} {'bblend':>7} {'reduce':>6} {'proj':>6} {'G/s':>5} {'slotMB':>6} "
          f"{'peakMB':>7}")
    w, h = (162, 105) if args.quick else (648, 420)
    label = f"garden {w}x{h}"
    for threads in sorted({1, ncpu}):
        print(row(label, threads, run(1, w, h, threads, rep)), flush=True)
    for simd in ("avx2", "scalar"):
        res = run(1, w, h, ncpu, rep, simd)
        print(row(f"  {res['best']['fs']['simd']} kernel", ncpu, res), flush=True)
    if not args.quick:
        res = run(5, 1920, 1080, ncpu, 6)
        print(row(f"grid-5 1920x1080 ({res['n'] / 1e6:.1f}M)", ncpu, res), flush=True)
    torch_ratio(args.quick)


if __name__ == "__main__":
    main()
