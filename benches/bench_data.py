"""Training-data throughput against what the tiny refiner consumes.

- disk: `PairDataset` clips/s (16 frames, 128x192 random crops, flips) through a DataLoader with
  0 and 2 workers, over a folder curated here from the built-in scenes (49-frame 832x480 PNG
  pairs, as `morphgs curate` writes by default);
- live: `LivePairs` clips/s (16-frame 256x256 pairs of the 100k-Gaussian built-in scenes,
  morphological, rendered in the workers) with 0 and 2 workers;
- the model: the tiny refiner's training clips/s at each clip shape (fp32, 2 threads, measured
  alone), so the loader's rate can be read against it: the data path keeps up when its clips/s
  is above the model's.

    python benches/bench_data.py            # full size (a few minutes on 2 cores)
    python benches/bench_data.py --quick    # smoke check
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any


def _rate(loader: Any, clips: int) -> float:
    it = iter(loader)
    next(it)  # workers started, first batch in
    t0 = time.perf_counter()
    n = 0
    while n < clips:
        b = next(it)
        n += int(b["corrupted"].shape[0])
    return n / (time.perf_counter() - t0)


def _model_rate(frames: int, h: int, w: int, steps: int) -> float:
    import torch

    from morphgs.models import ModelContext, create_model
    from morphgs.training import resolve_config

    torch.manual_seed(0)
    model = create_model("tiny", resolve_config("tiny", None).config.model_config, ModelContext(frames=frames))
    opt = torch.optim.AdamW(model.parameters(), lr=3e-4)
    x = torch.rand(1, 3, frames, h, w) * 2 - 1
    batch = {"corrupted": x, "clean": x.flip(-1)}
    times = []
    for i in range(steps + 1):
        t0 = time.perf_counter()
        loss, _ = model(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i:
            times.append(time.perf_counter() - t0)
    return 1.0 / sorted(times)[len(times) // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke check)")
    args = ap.parse_args()
    import torch

    import morphgs
    from morphgs.data import LivePairs, PairDataset

    torch.set_num_threads(2)
    if args.quick:
        size, frames, crop, disk_clips, live, live_clips, gaussians, steps = (96, 64), 8, (32, 64), 6, (32, 32), 4, \
            5000, 2
        f_live = 4
    else:
        size, frames, crop, disk_clips, live, live_clips, gaussians, steps = (832, 480), 49, (128, 192), 40, \
            (256, 256), 16, 100_000, 5
        f_live = 16
    f_disk = min(16, frames)
    work = Path(tempfile.mkdtemp(prefix="morphgs-bench-data-"))
    try:
        t0 = time.perf_counter()
        morphgs.curate([], work / "ds", pairs_per_scene=2, frames=frames, resolution=size, test_fraction=0.0,
                       builtin_gaussians=gaussians, progress=False)
        print(f"curated 4 pairs of {frames} frames at {size[0]}x{size[1]} in {time.perf_counter() - t0:.1f} s")
        ds = PairDataset(work / "ds", "train", frames=f_disk, size=crop, flip=True)
        print(f"disk: PairDataset, {f_disk}x{crop[0]}x{crop[1]} crops of {size[0]}x{size[1]} PNG pairs")
        for workers in (0, 2):
            loader = torch.utils.data.DataLoader(ds, batch_size=1, shuffle=True, num_workers=workers,
                                                 persistent_workers=False)
            print(f"  {workers} workers: {_rate(loader, disk_clips):6.2f} clips/s", flush=True)
        print(f"  tiny refiner training consumes {_model_rate(f_disk, *crop, steps):6.2f} clips/s "
              f"(batch 1, fp32, 2 threads)", flush=True)
        print(f"live: LivePairs, {f_live}x{live[0]}x{live[1]} pairs of {gaussians}-Gaussian built-in scenes, "
              "morphological")
        for workers in (0, 2):
            lp = LivePairs(frames=f_live, size=live, samples_per_epoch=10_000, builtin_gaussians=gaussians,
                           threads=1 if workers else 2)
            loader = torch.utils.data.DataLoader(lp, batch_size=1, num_workers=workers)
            print(f"  {workers} workers: {_rate(loader, live_clips):6.2f} clips/s", flush=True)
        print(f"  tiny refiner training consumes {_model_rate(f_live, *live, steps):6.2f} clips/s "
              f"(batch 1, fp32, 2 threads)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
