"""`morphgs fit`: reconstruct a 3DGS scene from posed images on the CPU (docs/fit.md).

The optimiser loop runs natively (`_core.Trainer`): INRIA / gsplat's recipe (L1 x 0.8 +
(1 - SSIM) x 0.2, Adam with per-array learning rates, the position lr decaying with the scene
scale, SH degree raised every 1000 steps), gsplat's `default` strategy (clone / split / prune,
opacity reset on) or `mcmc` (relocation, a Gaussian cap, position noise), deterministic for any
thread count and resumable bit for bit after a kill.

    from morphgs.fit import fit
    res = fit("dataset/", "runs/garden", views="every:8", config="sparse")
    res.heldout_psnr, res.ply

Importing this package never imports torch.
"""

from __future__ import annotations

from morphgs.fit.config import (
    DefaultStrategyConfig,
    FitConfig,
    FitConfigError,
    InitConfig,
    LearningRates,
    MCMCConfig,
    OutputConfig,
)
from morphgs.fit.data import FitDataError, PosedImages, load_posed_images
from morphgs.fit.init import InitError, initial_scene
from morphgs.fit.many import ManyResult, fit_many
from morphgs.fit.points import read_points
from morphgs.fit.run import FitPastError, FitResult, FitRunError, fit, scene_scale_of
from morphgs.fit.views import ViewSelection, ViewSelectionError, select_views

__all__ = [
    "DefaultStrategyConfig",
    "FitConfig",
    "FitConfigError",
    "FitDataError",
    "FitPastError",
    "FitResult",
    "FitRunError",
    "InitConfig",
    "InitError",
    "LearningRates",
    "ManyResult",
    "MCMCConfig",
    "OutputConfig",
    "PosedImages",
    "ViewSelection",
    "ViewSelectionError",
    "fit",
    "fit_many",
    "initial_scene",
    "load_posed_images",
    "read_points",
    "scene_scale_of",
    "select_views",
]
