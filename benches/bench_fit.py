"""`morphgs fit` benchmark: speed on the garden scene, quality over steps, sparse-view fits
(S_20 > S_40 > S_80), and the side-by-side with OpenSplat's CPU mode on the dataset of its
CPU measurements (docs/fit.md; rebuilt here from the built-in synthetic scene).

    python benches/bench_fit.py                    # everything (about 30-40 min on 2 idle cores)
    python benches/bench_fit.py --only garden      # garden | quality | sparse | opensplat
    python benches/bench_fit.py --quick            # tiny sizes, a smoke run
    python benches/bench_fit.py --only garden --baseline /tmp/old   # A/B against an older build

Sections:
- garden: 24 views of gsplat's garden profiling scene along a smooth path through its 3 cameras
  (648x420), a fit initialised from the garden points (111,785 Gaussians, 3-NN scales, opacity
  0.1); steps/s over the first steps (no densification yet) at 1 and 2 threads (a subprocess
  each), with the per-stage split and the process CPU time per step. With --baseline DIR (a
  folder holding an older build's `morphgs` package, e.g. a copy of python/morphgs with its
  `_core` built from main), the 2-thread garden step of that build and of this one alternate
  for --rounds rounds in the same session: per-round medians, then the median of each.
- quality: the same fit for `--quality-steps` steps with the default recipe: held-out PSNR/SSIM
  (every 8th view) and the Gaussian count over the steps.
- sparse: a 200k-Gaussian synthetic scene captured by 300 views along a 180-degree arc of its
  room orbit (test views: index % 8 == 0; S_K = every K-th view of the other 262), fitted with the
  `sparse` preset; held-out PSNR and seconds per K; the S_80 preview image is written with
  --write-docs.
- opensplat: the dataset of OpenSplat's CPU measurements on this machine type (docs/fit.md
  section 3: 40 views of the synthetic room at 320x240, 8 held out, 20,000 points from the ground
  truth) fitted by morphgs for 300 steps (no densification) and 1,500 steps (densify from step
  100 every 100 until 750): s/step and held-out PSNR. With --opensplat BIN (a CPU build of
  WebODM/OpenSplat, see docs/fit.md) OpenSplat runs on the same data in the same session;
  its published figures are printed as well.

Wall times on a shared machine are noisy; the process CPU time per step is printed beside them
(at 2 threads, wall >= CPU / 2).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIXTURES = Path(os.environ.get("MORPHGS_FIXTURES", REPO / "tests" / "fixtures"))
sys.path.insert(0, str(REPO / "tests"))
_GL = np.diag([1.0, -1.0, -1.0, 1.0])

# OpenSplat (WebODM/OpenSplat bd0400d, CPU mode) on this machine type, its CPU notes (docs/fit.md).
OPENSPLAT = {
    "s_per_it_1core": "0.258",
    "psnr_300": 22.14,
    "psnr_1500": 29.95,
    "gaussians_1500": 31_828,
}


def write_dataset(folder: Path, cams, images: np.ndarray, names: list[str] | None = None,
                  ply: str | None = None) -> None:
    """transforms.json + images/*.png for cameras and uint8 images."""
    from morphgs._core import _write_png_batch

    (folder / "images").mkdir(parents=True, exist_ok=True)
    names = names or [f"view_{i:04d}.png" for i in range(len(cams))]
    _write_png_batch([folder / "images" / n for n in names], np.ascontiguousarray(images))
    frames = [{"file_path": f"images/{n}", "transform_matrix": (c.camera_to_world @ _GL).tolist(),
               "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy} for n, c in zip(names, cams)]
    meta = {"w": cams[0].width, "h": cams[0].height, "frames": frames}
    if ply:
        meta["ply_file_path"] = ply
    (folder / "transforms.json").write_text(json.dumps(meta))


def garden_dataset(folder: Path, views: int) -> None:
    """The garden profiling scene's renders along a smooth path through its cameras, and the
    garden points as the initial cloud."""
    import morphgs
    from fit_helpers import write_point_ply
    from morphgs import trajectory
    from render_reference import garden

    scene, cams = garden(FIXTURES)
    path = trajectory.smooth_path(cams, views)
    write_dataset(folder, path, morphgs.render(scene, path).to_uint8(), ply="points.ply")
    d = np.load(FIXTURES / "gsplat_test_garden.npz")
    pts = d["means3d"].astype(np.float32)
    sel = np.all((pts >= -2) & (pts <= 2), axis=1)
    write_point_ply(folder / "points.ply", pts[sel], d["colors"][sel].astype(np.float64) / 255.0)


# ---- worker: one fit in its own process (thread count fixed per process) ----
def worker(args: argparse.Namespace) -> None:
    from morphgs.fit import FitConfig, fit

    cfg = FitConfig.from_dict(json.loads(args.config))
    rows: list[dict] = []

    def cb(kind: str, payload: object) -> None:
        if kind == "steps":
            rows.extend(payload)  # type: ignore[arg-type]

    c0 = time.process_time()
    t0 = time.perf_counter()
    res = fit(args.data, args.run, config=cfg, views=args.views, holdout=json.loads(args.holdout), init=args.init,
              progress=False, callback=cb)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    skip = min(10, len(rows) // 5)  # warm-up steps
    r = rows[skip:]
    stages = {k: float(np.mean([x[k] for x in r])) for k in ("seconds", "forward_s", "loss_s", "backward_s", "adam_s",
                                                            "strategy_s")} if r else {}
    ev = [line.split(",") for line in (Path(args.run) / "eval.csv").read_text().splitlines()[1:]]
    out = {"steps": res.steps, "gaussians": res.gaussians, "psnr": res.heldout_psnr, "ssim": res.heldout_ssim,
           "wall": wall, "cpu": cpu, "steps_per_s": len(r) / sum(x["seconds"] for x in r) if r else None,
           "stages": stages, "eval": [[int(e[0]), float(e[1]), float(e[2])] for e in ev],
           "gaussians_over_steps": [[x["step"], x["gaussians"]] for x in rows[:: max(1, len(rows) // 20)]],
           "train_views": len(res.train_views), "heldout_views": len(res.heldout_views)}
    print(json.dumps(out))


def run_fit(data: Path, run: Path, cfg: dict, *, threads: int, views: str = "all", holdout: object = "every:8",
            init: str = "auto") -> dict:
    env = dict(os.environ, MORPHGS_NUM_THREADS=str(threads))
    env.pop("RAYON_NUM_THREADS", None)
    cmd = [sys.executable, __file__, "--worker", "--data", str(data), "--run", str(run), "--config", json.dumps(cfg),
           "--views", views, "--holdout", json.dumps(holdout), "--init", init]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=7200)
    if out.returncode != 0:
        raise RuntimeError(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _load() -> str:
    return " ".join(open("/proc/loadavg").read().split()[:3]) if Path("/proc/loadavg").exists() else "?"


def section_garden(tmp: Path, quick: bool) -> None:
    data = tmp / "garden"
    garden_dataset(data, 8 if quick else 24)
    steps = 8 if quick else 150
    # the config keeps 30k steps (the real lr schedule); the run is cut after `steps`
    cfg = {"steps": 30_000}
    print(f"\n## garden 648x420, fit from the 111,785 garden points (load average {_load()})")
    print(f"{'threads':>7} {'steps':>6} {'steps/s':>8} {'ms/step':>8} {'CPU ms/step':>11}  "
          "forward  loss  backward  adam  (ms, mean)")
    for threads in (1, 2):
        res = run_fit_until(data, cfg, threads=threads, until=steps)
        s = res["stages"]
        print(f"{threads:>7} {res['steps']:>6} {res['steps_per_s']:>8.2f} {1e3 * s['seconds']:>8.1f} "
              f"{1e3 * res['cpu'] / res['steps']:>11.1f}  {1e3 * s['forward_s']:7.1f} {1e3 * s['loss_s']:5.1f} "
              f"{1e3 * s['backward_s']:9.1f} {1e3 * s['adam_s']:5.1f}")


def section_garden_ab(tmp: Path, quick: bool, baseline: str, rounds: int) -> None:
    """The 2-thread garden step of the build in `baseline` and of this one, alternating."""
    import statistics

    data = tmp / "garden"
    if not (data / "transforms.json").exists():
        garden_dataset(data, 8 if quick else 24)
    steps = 8 if quick else 60
    cfg = {"steps": 30_000}
    print(f"\n## garden A/B, 2 threads, {rounds} rounds of {steps} steps (load average {_load()})")
    print(f"{'build':>8} {'round':>5} {'steps/s':>8} {'ms/step':>8} {'CPU ms/step':>11}  forward  loss  backward  adam")
    res: dict[str, list[dict]] = {"baseline": [], "this": []}
    for r in range(rounds):
        for which in (("baseline", "this") if r % 2 == 0 else ("this", "baseline")):
            x = run_fit_until(data, cfg, threads=2, until=steps, baseline=baseline if which == "baseline" else None)
            res[which].append(x)
            st = x["stages"]
            print(f"{which:>8} {r:>5} {x['steps_per_s']:>8.2f} {1e3 * st['seconds']:>8.1f} "
                  f"{1e3 * x['cpu'] / x['steps']:>11.1f}  {1e3 * st['forward_s']:7.1f} {1e3 * st['loss_s']:5.1f} "
                  f"{1e3 * st['backward_s']:9.1f} {1e3 * st['adam_s']:5.1f}")
    med = {w: {k: statistics.median(x["stages"][k] for x in v) for k in ("seconds", "forward_s", "loss_s",
                                                                       "backward_s", "adam_s")}
           for w, v in res.items()}
    cpu = {w: statistics.median(x["cpu"] / x["steps"] for x in v) for w, v in res.items()}
    for w in ("baseline", "this"):
        m = med[w]
        print(f"{w:>8} median {1 / m['seconds']:>8.2f} {1e3 * m['seconds']:>8.1f} {1e3 * cpu[w]:>11.1f}  "
              f"{1e3 * m['forward_s']:7.1f} {1e3 * m['loss_s']:5.1f} {1e3 * m['backward_s']:9.1f} {1e3 * m['adam_s']:5.1f}")
    print(f"this / baseline: step {med['this']['seconds'] / med['baseline']['seconds']:.3f}, "
          f"backward {med['this']['backward_s'] / med['baseline']['backward_s']:.3f}, "
          f"CPU {cpu['this'] / cpu['baseline']:.3f}")


# a run cut after `until` steps (the config keeps its step count so the schedule is real)
UNTIL = """
import json, sys, time
import numpy as np
from morphgs.fit import FitConfig, load_posed_images, initial_scene, scene_scale_of
from morphgs import _core
data, cfg, until = sys.argv[1], FitConfig.from_dict(json.loads(sys.argv[2])), int(sys.argv[3])
posed = load_posed_images(data)
imgs, cams = posed.load(list(range(len(posed))))
scale = scene_scale_of(cams)
scene, _ = initial_scene("points", posed, np.stack([c.center for c in cams]), cfg, scene_scale=scale)
w2c = np.ascontiguousarray(np.stack([c.world_to_camera for c in cams])); K = np.ascontiguousarray(np.stack([c.K for c in cams]))
t = _core.Trainer(scene, imgs, w2c, K, config=cfg.native(scale))
rows = []
cb = lambda kind, p: rows.extend(p) if kind == "steps" else None
c0, t0 = time.process_time(), time.perf_counter()
t.run(until, callback=cb, progress_every=0.0)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
r = rows[min(10, len(rows) // 5):]
keys = ("seconds", "forward_s", "loss_s", "backward_s", "adam_s", "strategy_s")
print(json.dumps({"steps": len(rows), "wall": wall, "cpu": cpu, "steps_per_s": len(r) / sum(x["seconds"] for x in r),
                  "stages": {k: float(np.mean([x[k] for x in r])) for k in keys}, "gaussians": len(t)}))
"""


def run_fit_until(data: Path, cfg: dict, *, threads: int, until: int, baseline: str | None = None) -> dict:
    env = dict(os.environ, MORPHGS_NUM_THREADS=str(threads))
    env.pop("RAYON_NUM_THREADS", None)
    if baseline:
        env["PYTHONPATH"] = os.pathsep.join([baseline, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    out = subprocess.run([sys.executable, "-c", UNTIL, str(data), json.dumps(cfg), str(until)], env=env,
                         capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def section_quality(tmp: Path, quick: bool, steps: int) -> None:
    data = tmp / "garden"
    if not data.exists():
        garden_dataset(data, 8 if quick else 24)
    steps = 30 if quick else steps
    cfg = {"steps": steps, "output": {"eval_every": max(steps // 8, 1), "checkpoint_every": 0, "progress_every": 0.5}}
    print(f"\n## garden quality: the default recipe for {steps} steps, 2 threads (load average {_load()})")
    res = run_fit(data, tmp / "quality", cfg, threads=2, init="points")
    counts = dict((s, g) for s, g in res["gaussians_over_steps"])
    print(f"{res['train_views']} training / {res['heldout_views']} held-out views; {res['wall']:.0f} s wall, "
          f"{res['steps'] / res['wall']:.2f} steps/s overall")
    print(f"{'step':>6} {'held-out PSNR':>13} {'SSIM':>7} {'Gaussians (near)':>16}")
    for step, psnr, ssim in res["eval"]:
        near = counts[min(counts, key=lambda s: abs(s - step))]
        print(f"{step:>6} {psnr:>13.3f} {ssim:>7.4f} {near:>16}")


def sparse_capture(n_gaussians: int, size: tuple[int, int], views: int):
    import morphgs
    from morphgs import synthetic, trajectory

    scene = synthetic.scene(n_gaussians, sh_degree=3, seed=0)
    o = synthetic.suggested_orbit()
    # a 180-degree arc facing the walls (a capture that moves past the objects, as a DL3DV video
    # does), not a full orbit: every held-out view lies between training views
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], views, start_degrees=90.0,
                            arc_degrees=180.0, fov_y_degrees=50.0, resolution=size)
    return scene, cams, morphgs


def section_sparse(tmp: Path, quick: bool, size: tuple[int, int], steps: int, write_docs: bool,
                   ks: tuple[int, ...] = (20, 40, 80)) -> None:
    from morphgs.fit import FitConfig

    n, views = (20_000, 64) if quick else (200_000, 300)
    scene, cams, morphgs = sparse_capture(n, size, views)
    test = [i for i in range(views) if i % 8 == 0]
    traj = [i for i in range(views) if i % 8]
    ks = (2, 4, 8) if quick else ks
    steps = 40 if quick else steps
    print(f"\n## sparse-view fits of a {n:,}-Gaussian synthetic scene, {views}-view capture (180-degree arc) at "
          f"{size[0]}x{size[1]}, sparse preset ({steps} steps, MCMC cap 300k), 2 threads "
          f"(load average {_load()})")
    print(f"{'S_K':>5} {'views':>5} {'held-out PSNR':>13} {'SSIM':>7} {'Gaussians':>9} {'seconds':>8}")
    s80: tuple[int, np.ndarray] | None = None
    for k in ks:
        train = traj[::k]
        order = train + test
        data = tmp / f"sparse{k}"
        sub = morphgs.Cameras.from_list([cams[i] for i in order])
        write_dataset(data, sub, morphgs.render(scene, sub).to_uint8())
        cfg = FitConfig.preset("sparse").to_dict()
        cfg["steps"] = steps
        cfg["output"] = {"eval_every": steps, "checkpoint_every": 0, "preview_every": steps, "progress_every": 0.5}
        res = run_fit(data, tmp / f"run{k}", cfg, threads=2, views=",".join(map(str, range(len(train)))),
                      holdout=list(range(len(train), len(order))), init="random")
        print(f"{'S_' + str(k):>5} {len(train):>5} {res['psnr']:>13.3f} {res['ssim']:>7.4f} {res['gaussians']:>9} "
              f"{res['wall']:>8.0f}")
        if k == ks[-1]:
            # the held-out view farthest (along the capture) from every training view
            far = max(test, key=lambda i: min(abs(i - t) for t in train))
            fitted = morphgs.load(next((tmp / f"run{k}" / "point_cloud").glob("iteration_*/point_cloud.ply")))
            cam = cams[far]
            img = np.concatenate([np.rint(np.clip(morphgs.render(fitted, cam).rgb, 0, 1) * 255).astype(np.uint8),
                                  morphgs.render(scene, cam).to_uint8()], axis=1)
            s80 = (far, img)
    if write_docs and s80 is not None and not quick and ks[-1] == 80:
        from morphgs._core import _write_png

        _write_png(REPO / "docs" / "fit_s80_preview.png", np.ascontiguousarray(s80[1]))
        print(f"wrote docs/fit_s80_preview.png (capture view {s80[0]}, held out: S_80 reconstruction | ground truth)")


def opensplat_dataset(tmp: Path, quick: bool) -> tuple[Path, object, list[int]]:
    """The dataset of OpenSplat's CPU notes: 40 views of the synthetic room (100k Gaussians) at 320x240 on
    its orbit, views i % 5 == 0 held out, 20,000 points sampled from the ground-truth centres
    (opacity >= 0.1) with their colours as the initial cloud."""
    import morphgs
    from fit_helpers import write_point_ply
    from morphgs import synthetic

    w, h, views = (160, 120, 20) if quick else (320, 240, 40)
    scene = synthetic.scene(20_000 if quick else 100_000, sh_degree=3, seed=0)
    orb = synthetic.suggested_orbit()
    cams = morphgs.Cameras.from_list([morphgs.Camera.look_at(orb.eye(2 * np.pi * i / views), orb.center, (0.0, 0.0, 1.0),
                                                             fov_y_degrees=50.0, width=w, height=h)
                                      for i in range(views)])
    data = tmp / "osdata"
    write_dataset(data, cams, morphgs.render(scene, cams).to_uint8(), ply="init.ply")
    rng = np.random.default_rng(1)
    keep = np.flatnonzero(np.asarray(scene.opacities) >= 0.1)
    idx = rng.choice(keep, size=min(20_000, keep.size), replace=False)
    write_point_ply(data / "init.ply", np.asarray(scene.means)[idx], np.clip(np.asarray(scene.colors)[idx], 0, 1))
    return data, cams, [i for i in range(views) if i % 5 == 0]


def heldout_psnr(ply: Path, data: Path, cams, held: list[int], max_alpha: float) -> float:
    """Mean per-view PSNR of a PLY's renders (clamped) against the dataset's held-out images."""
    import morphgs
    from morphgs.media import read_image

    scene = morphgs.load(ply)
    sub = morphgs.Cameras.from_list([cams[i] for i in held])  # type: ignore[index]
    r = np.clip(morphgs.render(scene, sub, max_alpha=max_alpha).rgb, 0, 1)
    gt = np.stack([read_image(data / "images" / f"view_{i:04d}.png") for i in held]).astype(np.float32) / 255
    mse = ((r - gt) ** 2).mean(axis=(1, 2, 3))
    return float(np.mean(10 * np.log10(1 / mse)))


def run_opensplat(binary: str, data: Path, cams, held: list[int], out: Path, args: list[str], threads: int) -> dict:
    """OpenSplat on the training views of `data` (its own transforms.json): s/it from the times of
    its per-step lines (steps 2.. onwards), CPU time of the process, held-out PSNR of its PLY
    (rendered by morphgs with max_alpha 0.999, OpenSplat's cap)."""
    import resource

    osd = out / "osdata"
    (osd / "images").mkdir(parents=True, exist_ok=True)
    meta = json.loads((data / "transforms.json").read_text())
    frames = [f for i, f in enumerate(meta["frames"]) if i not in set(held)]
    for f in frames:
        shutil.copy(data / f["file_path"], osd / f["file_path"])
    shutil.copy(data / "init.ply", osd / "init.ply")
    c0 = cams[0]  # type: ignore[index]
    tf = {"camera_model": "OPENCV", "fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy, "w": c0.width,
          "h": c0.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "ply_file_path": "init.ply",
          "frames": [{"file_path": f["file_path"], "transform_matrix": f["transform_matrix"]} for f in frames]}
    (osd / "transforms.json").write_text(json.dumps(tf))
    ply = out / "opensplat.ply"
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.Popen([binary, str(osd), "-o", str(ply), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, env=env)
    times = []
    assert p.stdout is not None
    for line in p.stdout:
        if line.startswith("Step "):
            times.append(time.perf_counter())
    p.wait()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0 or not ply.exists():
        raise RuntimeError(f"OpenSplat failed ({p.returncode})")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    steps = len(times)
    return {"s_per_step": (times[-1] - times[0]) / max(steps - 1, 1), "cpu_per_step": cpu / max(steps, 1),
            "wall": wall, "psnr": heldout_psnr(ply, data, cams, held, 0.999), "steps": steps}


def section_opensplat(tmp: Path, quick: bool, binary: str | None) -> None:
    data, cams, held = opensplat_dataset(tmp, quick)
    c0 = cams[0]  # type: ignore[index]
    print(f"\n## side by side with OpenSplat (CPU): the dataset of OpenSplat's CPU notes, {len(cams)} views "  # type: ignore[arg-type]
          f"{c0.width}x{c0.height}, {len(held)} held out, 20,000 points from the ground truth (load average {_load()})")
    print(f"{'run':<50} {'s/step wall':>11} {'CPU s/step':>10} {'PSNR':>7} {'Gaussians':>9}")
    n300, n1500 = (30, 60) if quick else (300, 1500)
    runs = [(f"{n300} steps, defaults", {"steps": n300}, ["-n", str(n300)]),
            (f"{n1500} steps, densify from 100 every 100 to {n1500 // 2}",
             {"steps": n1500, "default": {"refine_start": 100, "refine_every": 100, "refine_stop": n1500 // 2}},
             ["-n", str(n1500), "--densify-from", "100", "--refine-every", "100"])]
    for label, cfg, os_args in runs:
        cfg = dict(cfg, output={"eval_every": cfg["steps"], "checkpoint_every": 0, "progress_every": 0.5})
        for threads in (2, 1):
            res = run_fit(data, tmp / f"os-{cfg['steps']}-{threads}", cfg, threads=threads, holdout=held, init="points")
            print(f"{'morphgs ' + label + f' ({threads} thr)':<50} {1 / res['steps_per_s']:>11.4f} "
                  f"{res['cpu'] / res['steps']:>10.4f} {res['psnr']:>7.2f} {res['gaussians']:>9}")
            if binary:
                o = run_opensplat(binary, data, cams, held, tmp / f"osrun-{cfg['steps']}-{threads}", os_args, threads)
                import morphgs

                n = len(morphgs.load(tmp / f"osrun-{cfg['steps']}-{threads}" / "opensplat.ply"))
                print(f"{'OpenSplat ' + label + f' ({threads} thr)':<50} {o['s_per_step']:>11.4f} "
                      f"{o['cpu_per_step']:>10.4f} {o['psnr']:>7.2f} {n:>9}")
    print(f"{'OpenSplat -n 300, cited (docs/fit.md)':<50} {'0.149-0.175':>11} {OPENSPLAT['s_per_it_1core']:>10} "
          f"{OPENSPLAT['psnr_300']:>7.2f} {20000:>9}")
    print(f"{'OpenSplat -n 1500 densify, cited (1 core)':<50} {'':>11} {'0.26-0.30':>10} {OPENSPLAT['psnr_1500']:>7.2f} "
          f"{OPENSPLAT['gaussians_1500']:>9}")
    print("OpenSplat makes 153 Adam updates in 300 iterations and 766 in 1,500 (its cadence); morphgs one per step. "
          "OpenSplat's PSNRs use max_alpha 0.999 (its cap), morphgs's its own 0.99.")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--data"), ap.add_argument("--run"), ap.add_argument("--config")
    ap.add_argument("--views", default="all"), ap.add_argument("--holdout", default='"every:8"')
    ap.add_argument("--init", default="auto")
    ap.add_argument("--only", choices=("garden", "quality", "sparse", "opensplat"), action="append")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a smoke run)")
    ap.add_argument("--quality-steps", type=int, default=2000)
    ap.add_argument("--sparse-size", default="416x240")
    ap.add_argument("--sparse-steps", type=int, default=3000)
    ap.add_argument("--sparse-k", default="20,40,80", help="the K of S_K, comma-separated (20,40,80)")
    ap.add_argument("--write-docs", action="store_true", help="write docs/fit_s80_preview.png")
    ap.add_argument("--opensplat", default=None, metavar="BIN",
                    help="an OpenSplat binary (CPU build) to run on the same data (else its figures are cited)")
    ap.add_argument("--dir", default=None, help="scratch folder (default: a temporary one, removed)")
    ap.add_argument("--baseline", default=None, metavar="DIR",
                    help="garden: also alternate with the older build whose morphgs package is in DIR")
    ap.add_argument("--rounds", type=int, default=4, help="rounds of the --baseline A/B (4)")
    a = ap.parse_args()
    if a.worker:
        worker(a)
        return
    if a.baseline and not (Path(a.baseline) / "morphgs" / "__init__.py").exists():
        raise SystemExit(f"bench_fit: error: --baseline {a.baseline} holds no morphgs package (morphgs/__init__.py)")
    sections = a.only or ["garden", "quality", "sparse", "opensplat"]
    size = tuple(int(v) for v in a.sparse_size.split("x"))
    tmp = Path(tempfile.mkdtemp(prefix="bench_fit_", dir=a.dir))
    try:
        print(f"morphgs fit benchmark; {os.cpu_count()} CPUs")
        if "garden" in sections:
            section_garden(tmp, a.quick)
            if a.baseline:
                section_garden_ab(tmp, a.quick, a.baseline, a.rounds)
        if "quality" in sections:
            section_quality(tmp, a.quick, a.quality_steps)
        if "sparse" in sections:
            section_sparse(tmp, a.quick, (96, 64) if a.quick else size, a.sparse_steps, a.write_docs,  # type: ignore[arg-type]
                           tuple(int(k) for k in a.sparse_k.split(",")))
        if "opensplat" in sections:
            section_opensplat(tmp, a.quick, a.opensplat)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
