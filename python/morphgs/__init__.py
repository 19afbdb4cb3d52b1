"""morphgs: optimisation-free, 3D-consistent corrupted/clean training pairs from 3DGS scenes.

Load a clean Gaussian-splat scene, perturb the Gaussians themselves (the paper's 3D morphological
perturbations and their spatial and radiometric siblings) and render the clean and the perturbed
scene along the same camera path.
"""

from __future__ import annotations

from morphgs._cli_warnings import install_from_environment as _install_cli_warnings
from morphgs._core import (
    GaussianScene,
    MorphgsError,
    MorphgsWarning,
    SceneFormatError,
    __version__,
    gaussian_blur,
    load,
    num_threads,
    save_compressed_ply,
    save_glb,
    save_ply,
    save_splat,
    save_spz,
)
from morphgs.saving import save
from morphgs.camera import Camera, Cameras
from morphgs.pair import Pair, render_pair
from morphgs import trajectory
# `morphgs.curate` and `morphgs.render` are the functions; their modules are `morphgs.curation` and
# `morphgs.rendering`.
from morphgs.curation import curate
from morphgs.rendering import Render, render, render_many
from morphgs import synthetic
from morphgs import exports
from morphgs.perturb import PerturbConfig, perturb

__all__ = [
    "Camera",
    "Cameras",
    "GaussianScene",
    "MorphgsError",
    "MorphgsWarning",
    "Pair",
    "PerturbConfig",
    "Render",
    "SceneFormatError",
    "__version__",
    "curate",
    "exports",
    "gaussian_blur",
    "load",
    "num_threads",
    "perturb",
    "render",
    "render_many",
    "render_pair",
    "save",
    "save_compressed_ply",
    "save_glb",
    "save_ply",
    "save_splat",
    "save_spz",
    "synthetic",
    "trajectory",
]

# a process started by a `morphgs` command (a spawned or Ray worker) shows its warnings as the
# command does: one line each
_install_cli_warnings()
