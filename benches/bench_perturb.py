"""Side-by-side benchmark of `morphgs.perturb` (issue 3).

For each preset, on a scene of 1M Gaussians with SH degree 3 (random arrays), it times:
  - morphgs:  morphgs.perturb (native, rayon, MORPHGS_NUM_THREADS threads, default 2);
  - numpy:    a vectorised NumPy implementation of the same SPEC §2 formulas (below), the
              baseline to beat by >= 4x;
  - copy:     np.copy of every scene array, the floor (morphgs should stay within 2x of it).
Each timing is the minimum over --reps interleaved repetitions.

    python benches/bench_perturb.py            # 1M Gaussians, 5 repetitions
    python benches/bench_perturb.py --quick    # 20k Gaussians, a smoke check
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("MORPHGS_NUM_THREADS", "2")

import numpy as np  # noqa: E402

import morphgs  # noqa: E402
from morphgs import PerturbConfig  # noqa: E402

C0 = np.float32(0.28209479177387814)
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest")


def random_arrays(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    f32 = np.float32
    quats = rng.standard_normal((n, 4), dtype=f32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return {
        "means": rng.standard_normal((n, 3), dtype=f32) * f32(5),
        "quats": quats,
        "log_scales": rng.standard_normal((n, 3), dtype=f32) - f32(4),
        "opacity_logits": rng.standard_normal(n, dtype=f32) * f32(2),
        "sh0": rng.standard_normal((n, 3), dtype=f32) * f32(0.5),
        "sh_rest": rng.standard_normal((n, 15, 3), dtype=f32) * f32(0.1),
    }


def numpy_perturb(a: dict[str, np.ndarray], cfg: PerturbConfig, seed: int) -> dict[str, np.ndarray]:
    """SPEC §2 with NumPy, float32 throughout: the baseline."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    n = len(a["opacity_logits"])
    if cfg.prune:
        keep = rng.random(n, dtype=f32) >= f32(cfg.prune)
        out = {k: a[k][keep] for k in FIELDS}
    else:
        out = {k: a[k].copy() for k in FIELDS}
    m = len(out["opacity_logits"])
    if cfg.position_jitter:
        e_avg = float((a["means"].max(axis=0) - a["means"].min(axis=0)).astype(np.float64).mean())
        out["means"] += f32(cfg.position_jitter * e_avg) * rng.standard_normal((m, 3), dtype=f32)
    if cfg.color_noise:
        c = f32(0.5) + C0 * out["sh0"]
        c += f32(cfg.color_noise) * rng.standard_normal((m, 3), dtype=f32)
        np.clip(c, 0, 1, out=c)
        out["sh0"] = (c - f32(0.5)) / C0
    if cfg.opacity_noise:
        alpha = f32(1) / (f32(1) + np.exp(-out["opacity_logits"]))
        alpha += f32(cfg.opacity_noise) * rng.standard_normal(m, dtype=f32)
        np.clip(alpha, f32(1e-4), f32(1 - 1e-4), out=alpha)
        out["opacity_logits"] = np.log(alpha / (f32(1) - alpha))
    if cfg.scale_noise:
        s = np.exp(out["log_scales"])
        s += f32(cfg.scale_noise) * rng.standard_normal((m, 3), dtype=f32)
        np.maximum(s, f32(1e-6), out=s)
        out["log_scales"] = np.log(s)
    if cfg.rotation_noise:
        q = out["quats"] / np.linalg.norm(out["quats"], axis=1, keepdims=True)
        q += f32(cfg.rotation_noise) * rng.standard_normal((m, 4), dtype=f32)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        out["quats"] = q
    return out


def best_of(reps: int, fns: dict[str, Callable[[], Any]]) -> dict[str, float]:
    """Minimum wall time in ms per function, repetitions interleaved so load hits all alike."""
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(reps):
        for name, fn in fns.items():
            t = time.perf_counter()
            result = fn()
            best[name] = min(best[name], (time.perf_counter() - t) * 1e3)
            del result
    return best


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="20k Gaussians, 2 repetitions (smoke check)")
    p.add_argument("--n", type=int, default=1_000_000, help="Gaussians (default 1M)")
    p.add_argument("--reps", type=int, default=5, help="repetitions per measurement (default 5)")
    args = p.parse_args(argv)
    n, reps = (20_000, 2) if args.quick else (args.n, args.reps)

    arrays = random_arrays(n)
    scene = morphgs.GaussianScene.from_arrays(**arrays)
    views = {k: getattr(scene, k) for k in FIELDS}
    mb = sum(v.nbytes for v in views.values()) / 1e6
    print(f"perturb benchmark: {n:,} Gaussians, SH degree 3 ({mb:.0f} MB of arrays), "
          f"morphgs threads {morphgs.num_threads()}, best of {reps}")
    print(f"{'preset':<14}{'morphgs ms':>11}{'numpy ms':>10}{'copy ms':>9}"
          f"{'vs numpy':>10}{'vs copy':>9}{'kept':>11}")
    ok = True
    for preset in ("spatial", "radiometric", "morphological", "naive"):
        cfg = PerturbConfig.preset(preset)
        t = best_of(reps, {
            "morphgs": lambda cfg=cfg: morphgs.perturb(scene, cfg, seed=7),
            "numpy": lambda cfg=cfg: numpy_perturb(views, cfg, 7),
            "copy": lambda: [np.copy(v) for v in views.values()],
        })
        kept = len(morphgs.perturb(scene, cfg, seed=7))
        speedup, vs_copy = t["numpy"] / t["morphgs"], t["morphgs"] / t["copy"]
        ok &= speedup >= 4 and vs_copy <= 2
        print(f"{preset:<14}{t['morphgs']:>11.1f}{t['numpy']:>10.1f}{t['copy']:>9.1f}"
              f"{speedup:>9.1f}x{vs_copy:>8.2f}x{kept:>11,}")
    print(f"targets (>= 4x faster than numpy, <= 2x the copy): {'met' if ok else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
