"""`--dry-run`'s cost estimate: seconds per stage from the plan's sizes and per-unit costs.

The unit costs are measured figures of the `smoke` preset on a quiet 2-core machine (see
docs/ablation.md) scaled linearly in pixels, frames, steps and Gaussians, so they are an
estimate: fits and rendering grow somewhat less than linearly in pixels, training less than
linearly in steps at small sizes. The sandbox/controlnet refiners are GPU models; their
training line is a GPU estimate (seconds per step on one data-centre GPU), labelled as such.
"""

from __future__ import annotations

from typing import Any

from morphgs.ablation.study import Study

__all__ = ["UNIT", "estimate"]

UNIT = {
    # measured on the 2-core machine (shared, not quiet) with a cut-down toy study: 4 built-in
    # scenes of 30k Gaussians at 128x128, 100-step fits, 30 training steps (docs/ablation.md)
    "render": 1.2e-11,      # s per (pixel x Gaussian) of a render incl. writing (captures: 0.5 s per 96 views)
    "fit": 6.0e-7,          # s per (pixel x step) of a sparse fit (1.0 s per 100 steps at 128x128)
    "refit": 1.3e-6,        # s per (pixel x step) of a re-fit with its scoring (2.1 s per 100 steps at 128x128)
    "train_tiny": 3.0e-6,   # s per (pixel x frame x step) of the default tiny refiner incl. CKA probes
    "refine": 1.1e-6,       # s per (pixel x frame) of refine + write
    "metrics2d": 1.2e-6,    # s per (pixel x frame): PSNR, SSIM, LPIPS, E_flow (DIS)
    "calibrate": 1.5,       # s per calibration stage besides its renders (statistics, goodness of fit, plots;
                            # the smoke preset's calibration takes 1.5 s in all)
    "gpu_step": 1.0,        # s per training step of the sandbox/controlnet refiners on one GPU (a guess)
}


def estimate(study: Study, jobs: list[Any]) -> dict[str, float]:
    """{stage: estimated seconds of the jobs still to do} (CPU seconds on 2 cores; training of
    GPU models in GPU seconds)."""
    from morphgs.ablation import cache
    from morphgs.ablation.jobs import resolve
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
            s = S["clean"]["steps"] * 2 * px * UNIT["fit"]
        elif st == "captures":
            s = S["capture"]["views"] * px * gauss * UNIT["render"]
        elif st == "trainsets":
            n = len(j.kwargs["scene_dirs"]) * S["conditions"]["pairs_per_scene"]
            s = n * frames * px * gauss * 2 * UNIT["render"]
            spec = resolve(j.kwargs["spec"])
            if getattr(spec, "kind", None) in FIT_KINDS:  # one fit per scene, to its end (underfit: its stop)
                steps = fit_steps(spec.params)
                if spec.kind == "underfit":
                    steps = stop_step(spec.params["fraction"], steps)
                s += len(j.kwargs["scene_dirs"]) * steps * px * UNIT["fit"]
        elif st == "calibration":
            # the strength scan and bisection (grid + ~10 points) plus op shares and the goodness of
            # fit render every calibration pair (half the training scenes' pairs) ~len(grid) + 15
            # times; x2 for perturbing, quantising and the statistics
            n = len(j.kwargs["scene_dirs"]) * S["conditions"]["pairs_per_scene"] / 2
            s = UNIT["calibrate"] + 2 * (len(j.kwargs["grid"]) + 15) * n * frames * px * gauss * UNIT["render"]
        elif st == "training":
            ch, cw = S["training"]["crop"]
            if S["model"]["name"] == "tiny":
                s = S["training"]["steps"] * ch * cw * S["training"]["window"] * UNIT["train_tiny"]
            else:
                s = S["training"]["steps"] * UNIT["gpu_step"]
        elif st == "testsets":
            s = S["sparse"]["steps"] * px * UNIT["fit"] + per_scene * frames * px * gauss * 2 * UNIT["render"]
        elif st == "refine":
            s = per_scene * frames * px * UNIT["refine"]
        elif st == "metrics2d":
            s = per_scene * frames * px * UNIT["metrics2d"]
        elif st == "metrics3d":
            s = per_scene * S["refit"]["steps"] * px * UNIT["refit"]
        else:
            s = 1.0
        out[st] = out.get(st, 0.0) + s
    return out
