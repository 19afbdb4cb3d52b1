"""The tiny refiner's speed: training steps/s and peak memory, and the time to refine a clip.

- training: batch 1 of 16x128x192 clips (the shipped tiny config), forward + L1/SSIM loss +
  backward + AdamW step, in fp32 and under bf16 autocast, with 1 and 2 torch threads; each
  setting runs in a fresh process so its peak resident memory (ru_maxrss) is its own; the
  memory right after building the model is reported beside it.
- refine: one 49-frame 832x480 clip (the synthetic scene rendered along an orbit) through
  `refine_clip`: 16-frame windows overlapping by 4 (4 windows), blending and colour correction.

    python benches/bench_train.py            # full size (a few minutes on 2 cores)
    python benches/bench_train.py --quick    # smoke check
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def train_worker(frames: int, h: int, w: int, steps: int, precision: str, threads: int) -> dict[str, float]:
    """Runs in its own process: steps/s and peak memory of one setting."""
    import torch

    from morphgs.models import ModelContext, create_model
    from morphgs.training import resolve_config

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    cfg = resolve_config("tiny", None).config
    model = create_model("tiny", cfg.model_config, ModelContext(frames=frames))
    opt = torch.optim.AdamW(model.parameters(), lr=3e-4, weight_decay=1e-2)
    g = torch.Generator().manual_seed(0)
    clean = torch.rand(1, 3, frames, h, w, generator=g) * 2 - 1
    corrupted = (clean + 0.1 * torch.randn(clean.shape, generator=g)).clamp(-1, 1)
    batch = {"corrupted": corrupted, "clean": clean}
    rss_model = _rss_mb()
    times = []
    for i in range(steps + 2):
        t0 = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            loss, _ = model(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if i >= 2:  # two warm-up steps
            times.append(time.perf_counter() - t0)
    times.sort()
    median = times[len(times) // 2]
    return {"steps_per_s": 1.0 / median, "step_s_median": median, "step_s_min": times[0],
            "rss_after_model_mb": rss_model, "peak_rss_mb": _rss_mb(),
            "parameters": float(sum(p.numel() for p in model.parameters()))}


def refine_bench(frames: int, w: int, h: int, threads: int) -> dict[str, float]:
    import numpy as np
    import torch

    import morphgs
    from morphgs import synthetic, trajectory
    from morphgs.color import reinhard_transfer
    from morphgs.inference import refine_clip
    from morphgs.models import ModelContext, create_model
    from morphgs.training import resolve_config

    torch.set_num_threads(threads)
    scene = synthetic.scene(n_gaussians=100_000, sh_degree=3, seed=0)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], frames, arc_degrees=60.0,
                            resolution=(w, h))
    clip = morphgs.render(scene, cams).to_uint8()
    assert clip.shape == (frames, h, w, 3)
    torch.manual_seed(0)
    cfg = resolve_config("tiny", None).config
    model = create_model("tiny", cfg.model_config, ModelContext(frames=16)).eval()
    with torch.no_grad():  # a trained-looking model: perturb the zero head so the output is not the input
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 1e-3)
    out = {}
    for precision in ("fp32", "bf16"):
        t0 = time.perf_counter()
        refined = refine_clip(model, clip, color_correct=False, autocast=precision == "bf16")
        out[f"refine_{precision}_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    reinhard_transfer(refined, clip)
    out["color_correct_s"] = time.perf_counter() - t0
    assert np.isfinite(refined).all()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke check)")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(train_worker(**json.loads(args.worker))))
        return
    frames, h, w, steps = (4, 32, 64, 2) if args.quick else (16, 128, 192, args.steps)
    print(f"tiny refiner training step, batch 1 of {frames}x{h}x{w}, median of {steps} steps")
    print(f"{'precision':>9} {'threads':>7} {'steps/s':>8} {'s/step':>7} {'RSS model MB':>13} {'peak RSS MB':>12}")
    env = {**os.environ, "OMP_NUM_THREADS": "2"}
    for precision in ("fp32", "bf16"):
        for threads in (1, 2):
            spec = json.dumps(dict(frames=frames, h=h, w=w, steps=steps, precision=precision, threads=threads))
            res = subprocess.run([sys.executable, __file__, "--worker", spec], capture_output=True, text=True,
                                 env=env, check=True)
            r = json.loads(res.stdout.strip().splitlines()[-1])
            print(f"{precision:>9} {threads:>7} {r['steps_per_s']:8.2f} {r['step_s_median']:7.3f} "
                  f"{r['rss_after_model_mb']:13.0f} {r['peak_rss_mb']:12.0f}", flush=True)
    rf, rw, rh = (8, 128, 64) if args.quick else (49, 832, 480)
    r = refine_bench(rf, rw, rh, threads=2)
    print(f"refine one {rf}-frame {rw}x{rh} clip (16-frame windows, overlap 4, 2 threads): "
          f"fp32 {r['refine_fp32_s']:.1f} s, bf16 {r['refine_bf16_s']:.1f} s; "
          f"colour correction {r['color_correct_s']:.2f} s")


if __name__ == "__main__":
    main()
