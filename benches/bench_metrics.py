"""Cost of each metric of `morphgs.metrics` on one 49-frame 832x480 clip pair (2 cores).

The pair is a render of the synthetic sample scene, clean vs morphologically perturbed (uint8
frames as read from disk, float32 depth, the cameras). Each metric runs once on the whole clip
after a warm-up on two frames; LPIPS is also reported as clips per second. torchmetrics' SSIM on
the same frames is the side-by-side reference (and a check: the two must agree to 1e-4).

    python benches/bench_metrics.py            # full size (a few minutes on 2 cores)
    python benches/bench_metrics.py --quick    # smoke check (tiny clip)
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def _time(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny clip (smoke check)")
    ap.add_argument("--frames", type=int, default=49)
    ap.add_argument("--size", default="832x480")
    ap.add_argument("--threads", type=int, default=2, help="torch, OpenCV and morphgs threads (2 = the target machine)")
    ap.add_argument("--no-vgg", action="store_true", help="skip LPIPS-VGG (the slowest row)")
    ap.add_argument("--no-torchmetrics", action="store_true", help="skip the torchmetrics SSIM reference")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.size = 4, "96x64"
    os.environ["MORPHGS_NUM_THREADS"] = str(args.threads)
    w, h = (int(v) for v in args.size.split("x"))

    import cv2
    import torch

    import morphgs
    from morphgs import metrics, synthetic, trajectory

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    scene = synthetic.scene(n_gaussians=20_000 if args.quick else 200_000, sh_degree=3, seed=0)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], args.frames, start_degrees=135,
                            arc_degrees=30, resolution=(w, h))
    pair = morphgs.render_pair(scene, cams, config="morphological", seed=1)
    pred, gt = pair.corrupted.to_uint8(), pair.clean.to_uint8()
    d_pred, d_gt = pair.corrupted.depth, pair.clean.depth
    n = len(gt)

    rows: list[tuple[str, float, str]] = []

    def run(name: str, fn: Callable[[], Any], note: str = "") -> Any:
        seconds, out = _time(fn)
        rows.append((name, seconds, note))
        print(f"  {name}: {seconds:.2f} s", file=sys.stderr, flush=True)
        return out

    # warm-ups (imports, model loading, OpenCV thread pool) on two frames
    metrics.ssim(pred[:2], gt[:2])
    metrics.lpips(pred[:2], gt[:2])
    metrics.flow_epe(pred[:2], gt[:2])

    run("psnr", lambda: metrics.psnr(pred, gt, reduction="none"))
    run("color_shift (mean CIELAB Delta E)", lambda: metrics.color_shift(pred, gt, reduction="none"))
    ours_ssim = run("ssim (OpenCV filter, float32)", lambda: metrics.ssim(pred, gt, reduction="none"))
    from morphgs.metrics import image as image_mod

    have = image_mod._have_cv2
    image_mod._have_cv2 = lambda: False  # type: ignore[assignment]
    try:
        run("ssim (numpy filter, float32)", lambda: metrics.ssim(pred, gt, reduction="none"))
    finally:
        image_mod._have_cv2 = have  # type: ignore[assignment]
    if not args.no_torchmetrics:
        try:
            from torchmetrics.functional.image import structural_similarity_index_measure as tm_ssim
        except ImportError:
            tm_ssim = None  # type: ignore[assignment]
        if tm_ssim is not None:
            tp = torch.from_numpy(pred).permute(0, 3, 1, 2).float() / 255
            tg = torch.from_numpy(gt).permute(0, 3, 1, 2).float() / 255
            with torch.inference_mode():
                ref = run("ssim, torchmetrics (reference)", lambda: tm_ssim(tp, tg, data_range=1.0, reduction="none"))
            gap = float(np.abs(np.asarray(ref, dtype=np.float64) - ours_ssim).max())
            if gap > 1e-4:
                print(f"SSIM disagrees with torchmetrics by {gap}", file=sys.stderr)
                return 1
            rows[-1] = (rows[-1][0], rows[-1][1], f"max abs difference from ours {gap:.1e}")
    lp = run("lpips alex", lambda: metrics.lpips(pred, gt, reduction="none"))
    if not args.no_vgg:
        run("lpips vgg", lambda: metrics.lpips(pred, gt, net="vgg", reduction="none"))
    run("E_flow + E_warp (DIS reference)", lambda: metrics.temporal_errors(pred, gt))
    run("E_flow (DIS reference)", lambda: metrics.flow_epe(pred, gt, reduction="none"))
    flows, valid = run("geometric flows", lambda: metrics.geometric_flows(d_gt, cams))
    run("E_flow + E_warp (geometric reference)", lambda: metrics.temporal_errors(pred, gt, flow=flows, valid=valid))
    run("depth errors", lambda: metrics.depth_metrics(d_pred, d_gt, reduction="none"))
    a = metrics.backproject_depth(d_pred[0], cams[0])
    b = metrics.backproject_depth(d_gt[0], cams[0])
    run("chamfer + F-score, one frame", lambda: metrics.point_cloud_metrics(a, b, threshold=0.01),
        f"{len(a)} vs {len(b)} points")
    rng = np.random.default_rng(0)
    rows_cka = 1_000 if args.quick else 20_000
    fx, fy = rng.normal(size=(rows_cka, 320)), rng.normal(size=(rows_cka, 320))
    run(f"linear CKA ({rows_cka} x 320 features)", lambda: metrics.linear_cka(fx, fy))

    print(f"\nmorphgs.metrics on one {n}-frame {w}x{h} clip pair, {args.threads} threads "
          f"(torch {torch.__version__}, OpenCV {cv2.__version__})\n")
    print("| metric | seconds per clip | frames/s | note |\n|---|---|---|---|")
    for name, seconds, note in rows:
        print(f"| {name} | {seconds:.2f} | {n / seconds:.1f} | {note} |")
    alex = next(s for name, s, _ in rows if name == "lpips alex")
    print(f"\nLPIPS (alex): {1 / alex:.3f} clips/s ({n / alex:.1f} frame pairs/s); mean {float(np.mean(lp)):.4f}")
    vgg = [s for name, s, _ in rows if name == "lpips vgg"]
    if vgg:
        print(f"LPIPS (vgg): {1 / vgg[0]:.3f} clips/s ({n / vgg[0]:.1f} frame pairs/s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
