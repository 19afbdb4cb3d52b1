"""`--dry-run`'s cost estimate: seconds per stage from the plan's sizes and per-unit costs.

The unit costs were measured on a quiet 2-core AMD EPYC (Zen 5, `lscpu` family 26) running the toy
preset with `-j 2` (docs/ablation.md, "What `--dry-run` is calibrated on"); the same study took 2-3x
longer on the Zen 3 and Zen 4 machines of earlier sessions, so read the estimate as a lower bound
on a slower or shared CPU. Renders, training and metrics scale linearly in pixels, frames and steps;
fits (sparse, clean, the re-fits) by their pixels and by their mean Gaussian count under the MCMC
growth schedule (`mean_gaussians`), which sets their cost at the study sizes. The
sandbox/controlnet refiners are GPU models; their training line is a GPU estimate (seconds per step
on one data-centre GPU), labelled as such.
"""

from __future__ import annotations

from typing import Any

from morphgs.ablation.study import Study

__all__ = ["UNIT", "estimate", "fit_seconds", "mean_gaussians"]

UNIT = {
    # per job, in seconds of the 2-core machine (a job's single-thread seconds / 2 under -j 2):
    # toy preset, 128x128, 30k-Gaussian rooms; docs/ablation.md
    "render": 4.5e-12,      # s per (pixel x Gaussian) of a render incl. writing (captures: 0.18 s per 96 views)
    # a fit's step costs a pixel term and a Gaussian term; at the study sizes the Gaussians set it
    # (a 3,000-step toy fit: 4.3 ms a step at 20k Gaussians, 12.4 ms over its last 1,000 steps as
    # it grows from 40k to the 60k cap, one thread; 0.72x the Gaussian term of before the MCMC
    # noise was vectorised, which took the toy study's fit stages to 0.73x their job-seconds)
    "fit": 2.5e-8,          # s per (pixel x step) of a fit (sparse, clean or re-fit)
    "fit_gauss": 8.6e-8,    # s per (Gaussian x step) of a fit (the mean count of `mean_gaussians`)
    "score3d": 0.05,        # s per re-fit besides the fit: rendering and scoring it
    "train_tiny": 7.5e-7,   # s per (pixel x frame x step) of the default tiny refiner incl. CKA probes (toy: 29.4 s a run;
                            # 38.8 s before its SSIM term and AdamW ran natively, docs/training.md)
    "refine": 3.2e-7,       # s per (pixel x frame) of refine + write
    "metrics2d": 4.0e-7,    # s per (pixel x frame): PSNR, SSIM, LPIPS, E_flow (DIS)
    "calibrate": 1.5,       # s per calibration stage besides its renders (statistics, goodness of fit, plots;
                            # the smoke preset's calibration takes 1.5 s in all)
    "realism_trial": 0.39,  # a realism search's candidate (a strength match and a cross-fitted CNN), as a share
                            # of the PSNR calibration (toy: 240-271 s a search of 16 against 23 s, one thread)
    "gpu_step": 1.0,        # s per training step of the sandbox/controlnet refiners on one GPU (a guess)
}


def mean_gaussians(start: int, cap: int, steps: int, *, refine_start: int | None = None,
                   refine_every: int | None = None, refine_stop: int | None = None) -> float:
    """The mean Gaussian count over a fit's `steps` under the MCMC strategy's growth (+5 % at
    every `refine_every`-th step after `refine_start` and before `refine_stop`, at most `cap`; morphgs.fit's
    defaults where not given), starting from `start` (the random or SfM initial points)."""
    from morphgs.fit.config import MCMCConfig

    m = MCMCConfig()
    start_at = m.refine_start if refine_start is None else refine_start
    every = m.refine_every if refine_every is None else refine_every
    stop = m.refine_stop if refine_stop is None else refine_stop
    n, total, last = float(min(start, cap)), 0.0, 0
    first = (start_at // every + 1) * every  # the steps that grow: start < t < stop, t % every == 0
    for t in range(first, min(steps + 1, stop), every):
        total += n * (t - last)
        last, n = t, min(float(cap), float(int(1.05 * n)))
        if n >= cap:
            break
    return (total + n * (steps - last)) / max(steps, 1)


def fit_seconds(steps: int, px: int, fit: dict[str, Any]) -> float:
    """Estimated seconds of a fit of `steps` at `px` pixels with a settings table's
    `random_points` and `cap_max` (captures with SfM points start from theirs; counted as the
    random points)."""
    g = mean_gaussians(int(fit["random_points"]), int(fit["cap_max"]), steps)
    return steps * (px * UNIT["fit"] + g * UNIT["fit_gauss"])


def _fit_settings(params: dict[str, Any]) -> dict[str, int]:
    """A real-fit condition's initial points and cap, from the FitConfig curate fits it with
    (`curation.fits.fit_config`: the `sparse` preset and the condition's "fit" overrides; a target
    carries the study's `[sparse]` ones)."""
    from morphgs.curation.fits import fit_config

    cfg = fit_config(params, "the estimate", 0)
    return {"random_points": int(cfg.init.random_points), "cap_max": int(cfg.mcmc.cap_max)}


def estimate(study: Study, jobs: list[Any]) -> dict[str, float]:
    """{stage: estimated seconds of the jobs still to do} (CPU seconds on 2 cores; training of
    GPU models in GPU seconds)."""
    from morphgs.ablation import cache
    from morphgs.ablation.jobs import resolve
    from morphgs.calibration.objective import TRIALS
    from morphgs.curation.plan import FIT_KINDS, fit_steps, stop_step

    S = study.settings
    w, h = S["capture"]["size"]
    px = w * h
    gauss = S["scenes"]["builtin_gaussians"] if not S["scenes"]["inputs"] else 500_000
    frames = S["clips"]["frames"]
    per_scene = S["clips"]["per_scene"]
    out: dict[str, float] = {}
    for j in jobs:
        if cache.is_done(j.ref):
            continue
        st = j.ref.stage
        if st == "cleanfits":  # the photos shrunk to 1-2x the study size a side: ~2x its pixels
            s = fit_seconds(S["clean"]["steps"], 2 * px, S["clean"])
        elif st == "captures":
            s = S["capture"]["views"] * px * gauss * UNIT["render"]
        elif st in ("trainsets", "pairfits"):
            scenes = len(j.kwargs["scene_dirs"]) if st == "trainsets" else 1
            s = scenes * S["conditions"]["pairs_per_scene"] * frames * px * gauss * 2 * UNIT["render"]
            spec = resolve(j.kwargs["spec"])
            # a fit per scene, to its end (underfit: its stop): in the pairfits jobs (a training set
            # without them fits its scenes itself)
            if getattr(spec, "kind", None) in FIT_KINDS and (st == "pairfits" or not j.kwargs["fits"]):
                steps = fit_steps(spec.params)
                if spec.kind == "underfit":
                    steps = stop_step(spec.params["fraction"], steps)
                s += scenes * fit_seconds(steps, px, _fit_settings(spec.params))
        elif st == "calibration":
            # the strength scan and bisection (grid + ~10 points) plus op shares and the goodness of
            # fit render every calibration pair (half the training scenes' pairs) ~len(grid) + 15
            # times; x2 for perturbing, quantising and the statistics
            n = len(j.kwargs["scene_dirs"]) * S["conditions"]["pairs_per_scene"] / 2
            s = UNIT["calibrate"] + 2 * (len(j.kwargs["grid"]) + 15) * n * frames * px * gauss * UNIT["render"]
            if j.kwargs.get("objective") == "realism":  # the op-mix search first: TRIALS candidates
                s *= 1 + TRIALS * UNIT["realism_trial"]
        elif st == "training":
            ch, cw = S["training"]["crop"]
            if S["model"]["name"] == "tiny":
                s = S["training"]["steps"] * ch * cw * S["training"]["window"] * UNIT["train_tiny"]
            else:
                s = S["training"]["steps"] * UNIT["gpu_step"]
        elif st == "testsets":
            s = fit_seconds(S["sparse"]["steps"], px, S["sparse"]) + per_scene * frames * px * gauss * 2 * UNIT["render"]
        elif st == "refine":
            s = per_scene * frames * px * UNIT["refine"]
        elif st == "metrics2d":
            s = per_scene * frames * px * UNIT["metrics2d"]
        elif st == "metrics3d":
            s = per_scene * (fit_seconds(S["refit"]["steps"], px, S["refit"]) + UNIT["score3d"])
        else:
            s = 1.0
        out[st] = out.get(st, 0.0) + s
    return out


# bytes of one Gaussian while it is fitted: 59 float32 parameters, their gradients and Adam's two
# moments (4 x 59 x 4 B), rounded up for the renderer's per-Gaussian buffers
FIT_BYTES_PER_GAUSSIAN = 1024
SCENE_BYTES_PER_GAUSSIAN = 248  # a loaded scene (INRIA PLY layout, SH degree 3)
BASE_BYTES = 400e6              # the Python process with NumPy and the extension
TORCH_BYTES = 900e6             # ... and torch with a small model
# the GPU refiners' memory per GPU, from docs/refiners.md (estimates: no GPU run measured them)
GPU_MEMORY = {"sandbox": ("1 GPU", 24e9), "controlnet": ("8 GPUs (FSDP2)", 26e9)}


def parse_cluster(text: str) -> tuple[int, int, int]:
    """`NODESxCPUS` or `NODESxCPUSxGPUS` (GPUs per node) -> (nodes, cpus, gpus); ValueError else."""
    parts = text.lower().split("x")
    try:
        vals = [int(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or any(v < 0 for v in vals) or vals[0] < 1 or vals[1] < 1:
        raise ValueError(f"--cluster {text!r}: expected NODESxCPUS or NODESxCPUSxGPUS, e.g. 8x32x8")
    return vals[0], vals[1], vals[2] if len(vals) == 3 else 0


def peak_memory(study: Study, stage: str) -> float:
    """Estimated peak host memory of one job of a stage, in bytes (sizes of what it holds)."""
    S = study.settings
    w, h = S["capture"]["size"]
    px = w * h
    gauss = S["scenes"]["builtin_gaussians"] if not S["scenes"]["inputs"] else 500_000
    views = S["capture"]["views"]
    frames, img = S["clips"]["frames"], 3 * 4 * px  # a float32 RGB frame

    def fit(cap: int) -> float:
        return BASE_BYTES + cap * FIT_BYTES_PER_GAUSSIAN + 2 * views * img

    if stage == "cleanfits":
        return fit(int(S["clean"]["cap_max"]))
    if stage in ("captures", "calibration"):
        return BASE_BYTES + gauss * SCENE_BYTES_PER_GAUSSIAN * 2 + views * img
    if stage == "pairfits":
        return fit(int(S["sparse"]["cap_max"]))
    if stage == "trainsets":  # a perturbed render of the scene (a fit when it has no pairfits)
        return max(fit(int(S["sparse"]["cap_max"])), BASE_BYTES + gauss * SCENE_BYTES_PER_GAUSSIAN * 2 + 2 * frames * img)
    if stage == "testsets":
        return max(fit(int(S["sparse"]["cap_max"])), BASE_BYTES + gauss * SCENE_BYTES_PER_GAUSSIAN + 4 * frames * img)
    if stage == "metrics3d":
        return fit(int(S["refit"]["cap_max"])) + TORCH_BYTES
    if stage == "training" and S["model"]["name"] != "tiny":
        return TORCH_BYTES + 8e9  # the host side of a GPU run: the frozen weights staged once
    return BASE_BYTES + TORCH_BYTES + 8 * frames * img


def _gb(b: float) -> str:
    return f"{b / 1e9:.1f} GB"


def cluster_plan(study: Study, jobs: list[Any], cluster: tuple[int, int, int], threads: int) -> list[str]:
    """Lines of `--dry-run --backend ray`: per stage its jobs, CPU-hours, GPU-hours, peak memory per
    job, and how its jobs spread over the nodes (Ray tasks of `threads` CPUs, the stages run level
    by level): jobs at a time, waves, and the stage's wall time at that spread."""
    from morphgs.ablation.stages import STAGES

    nodes, cpus, gpus = cluster
    model = study["model"]["name"]
    per_stage: dict[str, list[Any]] = {}
    for j in jobs:
        per_stage.setdefault(j.ref.stage, []).append(j)
    est = estimate(study, jobs)  # seconds on 2 cores (CPU stages use both; GPU training: GPU seconds)
    slots = nodes * max(1, cpus // threads)
    lines = [f"cluster plan: {nodes} node(s) x {cpus} CPUs" + (f" x {gpus} GPUs" if gpus else "")
             + f"; Ray tasks of {threads} CPU(s), {slots} at a time (an estimate from the 2-core unit costs; "
             "memory from the sizes each job holds)",
             "stage        jobs    CPU-h    GPU-h   wall      peak mem/job              spread"]
    cpu_total = gpu_total = wall = 0.0
    for st in STAGES:
        js = per_stage.get(st, [])
        if not js:
            continue
        s = est.get(st, 0.0)
        gpu_stage = st == "training" and model != "tiny"
        if gpu_stage:
            need, per_gpu = GPU_MEMORY.get(model, ("1 GPU", 24e9))
            n_gpu = 8 if need.startswith("8") else 1
            gpu_h, cpu_h = s * n_gpu / 3600, 0.0
            mem = f"{_gb(peak_memory(study, st))} + {_gb(per_gpu)}/GPU"
            at_once = max(1, (nodes * gpus) // n_gpu) if gpus else 0
            spread = (f"{at_once} run(s) at a time on {need} each" if at_once else f"needs {need} each: no GPUs given")
            per_job = s / len(js)
            st_wall = (-(-len(js) // at_once)) * per_job if at_once else float("inf")
        else:
            cpu_h, gpu_h = s * 2 / 3600, 0.0
            mem = _gb(peak_memory(study, st))
            at_once = min(len(js), slots)
            waves = -(-len(js) // at_once)
            per_job = s * 2 / len(js) / threads  # CPU-seconds over the task's CPUs (linear: an estimate)
            per_node = -(-len(js) // nodes)
            spread = f"{per_node} per node, {waves} wave(s) of {at_once}"
            st_wall = waves * per_job
        cpu_total += cpu_h
        gpu_total += gpu_h
        wall += st_wall
        w_txt = "n/a" if st_wall == float("inf") else f"{st_wall / 3600:.1f} h"
        lines.append(f"{st:<12} {len(js):>5} {cpu_h:>8.1f} {gpu_h:>8.1f}   {w_txt:<9} {mem:<25} {spread}")
    when = "n/a (no GPUs for the GPU training)" if wall == float("inf") else f"{wall / 3600:.1f} h"
    lines.append(f"total: {cpu_total:.1f} CPU-h, {gpu_total:.1f} GPU-h; wall about {when} "
                 "(stages one after another, each spread as shown)")
    return lines
