"""Clean/corrupted render pairs (SPEC §5): one scene load, one perturbation, both sequences
rendered along the same cameras in one parallel pass of the multi-scene renderer.

`config="blur2d"` is the paper's 2D baseline ("2D Render Blur"): the corrupted frames are the
clean frames blurred by a separable Gaussian of `blur_sigma` pixels (native, parallel); depth and
alpha are the clean ones (the blur is image-space only).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from morphgs.camera import Camera, Cameras

__all__ = ["Pair", "render_pair"]


def _as_cameras(cameras: Camera | Cameras | Sequence[Camera]) -> Cameras:
    if isinstance(cameras, Cameras):
        return cameras
    if isinstance(cameras, Camera):
        return Cameras.from_list([cameras])
    return Cameras.from_list(list(cameras))


@dataclass(frozen=True)
class Corruption:
    """What a pair does to the clean scene: a perturbation config, or the 2D blur baseline."""

    kind: str  # "perturb" | "strength" | "blur2d" | "sparse" | "underfit" | "cross" (the last three:
    # the corrupted scene is a real fit, see morphgs.curation.fits; `corrupt_scene` cannot make it)
    config: dict[str, Any]
    perturb_config: Any = None
    blur_sigma: float = 0.0

    @classmethod
    def make(cls, config: Any, *, blur_sigma: float = 2.0) -> Corruption:
        """From a preset name, "blur2d", a PerturbConfig, a `Strength`, a dict
        (`PerturbConfig.to_dict()`, {"kind": "blur2d", "sigma": s} or {"kind": "strength", ...},
        see morphgs.strength) or a curate ConfigSpec."""
        import morphgs
        from morphgs.strength import Strength, check_quantiles

        kind = getattr(config, "kind", None)
        params = getattr(config, "params", None)
        if isinstance(kind, str) and isinstance(params, dict):  # ConfigSpec
            if kind in ("sparse", "underfit", "cross"):
                return cls(kind, {"kind": kind, **params})
            if kind in ("blur2d", "strength"):
                return cls.make({"kind": kind, **params})
            config = params
        if isinstance(config, Strength):
            return cls("strength", config.to_dict())
        if isinstance(config, str):
            if config.lower() == "blur2d":
                return cls.make({"kind": "blur2d", "sigma": blur_sigma})
            config = morphgs.PerturbConfig.preset(config)
        if isinstance(config, Mapping):
            if config.get("kind") == "blur2d":
                if "quantiles" in config:  # a sigma distribution: each pair draws (`for_seed`)
                    _, sig = check_quantiles(config["quantiles"])
                    if sig[-1] > 256.0:
                        raise ValueError(f"blur sigma must be in [0, 256] pixels, got quantiles up to {sig[-1]}")
                    return cls("blur2d", {"kind": "blur2d", "quantiles": config["quantiles"]}, None, float("nan"))
                sigma = float(config.get("sigma", blur_sigma))
                if not np.isfinite(sigma) or not 0.0 <= sigma <= 256.0:
                    raise ValueError(f"blur sigma must be in [0, 256] pixels, got {sigma}")
                return cls("blur2d", {"kind": "blur2d", "sigma": sigma}, None, sigma)
            if config.get("kind") == "strength":
                d = dict(config)
                if "quantiles" in d:
                    check_quantiles(d["quantiles"])
                Strength.from_dict({k: v for k, v in d.items() if k != "quantiles"})  # validate
                return cls("strength", d)
            config = morphgs.PerturbConfig.from_dict({k: v for k, v in config.items() if k not in ("kind", "name")})
        if not isinstance(config, morphgs.PerturbConfig):
            raise TypeError(f"config must be a preset name, 'blur2d', a PerturbConfig or a dict, got {type(config)}")
        return cls("perturb", dict(config.to_dict()), config)

    def strength(self, seed: int) -> float | None:
        """The strength a "strength" corruption uses for pair seed `seed` (drawn from its quantile
        table when it has one), or the sigma a blur2d sigma distribution draws; None otherwise."""
        if self.kind != "strength" and not (self.kind == "blur2d" and "quantiles" in self.config):
            return None
        from morphgs.strength import draw_strength

        return draw_strength(self.config, seed)

    def for_seed(self, seed: int) -> Corruption:
        """The corruption of the pair of seed `seed`: a blur2d sigma distribution with its sigma
        drawn (as a strength distribution's strength, `morphgs.strength.draw_strength`); the
        others as they are."""
        if self.kind == "blur2d" and "quantiles" in self.config:
            return Corruption("blur2d", self.config, None, float(self.strength(seed) or 0.0))
        return self

    def corrupt_scene(self, scene: Any, seed: int, cameras: Any = None) -> Any:
        """The perturbed copy of `scene` (None for blur2d and the real fits); `cameras` are the pair's,
        whose every K-th the sparse-view ops of a strength config take as training views."""
        if self.kind == "strength":
            from morphgs.strength import from_config

            return from_config(self.config, seed).apply(scene, seed=seed, cameras=cameras)
        if self.kind != "perturb":
            return None
        import morphgs

        return morphgs.perturb(scene, self.perturb_config, seed=seed)


def iter_pair_chunks(
    scene: Any,
    corrupted_scene: Any,
    corruption: Corruption,
    cameras: Cameras,
    *,
    chunk: int,
    **render_options: Any,
) -> Iterator[tuple[int, Any, Any, float]]:
    """Render a pair `chunk` frames at a time (both scenes in one parallel pass per chunk).

    Yields (start, clean Render, corrupted Render, seconds) per chunk.
    """
    for start in range(0, len(cameras), chunk):
        t0 = time.perf_counter()
        clean, corrupted = _render_both(scene, corrupted_scene, corruption, cameras[start:start + chunk],
                                        **render_options)
        yield start, clean, corrupted, time.perf_counter() - t0


def _render_both(scene: Any, corrupted_scene: Any, corruption: Corruption, cameras: Cameras,
                 **render_options: Any) -> tuple[Any, Any]:
    """The clean and corrupted frames of `cameras`. A corrupted scene with popping caps (the
    extras `morphgs.strength.POPPING_EXTRAS`) pops here as in every render: the native renderer
    hides, per camera, what its caps hide, so no caller can forget it."""
    from morphgs._core import gaussian_blur
    from morphgs.rendering import Render, render_many

    if corruption.kind == "blur2d":
        (clean,) = render_many([scene], cameras, **render_options)
        blurred = gaussian_blur(np.ascontiguousarray(clean.rgb), corruption.blur_sigma)
        return clean, Render(blurred, clean.depth, clean.alpha, clean.stats)
    clean, corrupted = render_many([scene, corrupted_scene], cameras, **render_options)
    return clean, corrupted


@dataclass(frozen=True)
class Pair:
    """A clean/corrupted render pair along one camera path.

    Attributes:
        clean, corrupted: the two Render results (rgb (F,H,W,3), depth, alpha).
        config: the corruption as a dict (`PerturbConfig.to_dict()`, or {"kind": "blur2d",
            "sigma": s}).
        seed: the perturbation seed.
        cameras: the cameras both sequences were rendered from.
        timings: seconds spent loading, perturbing and rendering.
    """

    clean: Any
    corrupted: Any
    config: dict[str, Any]
    seed: int
    cameras: Cameras
    timings: dict[str, float] = field(default_factory=dict)

    def save(self, folder: str | os.PathLike[str]) -> None:
        """Write `clean/` and `corrupted/` (each through Render.save) under `folder`."""
        from pathlib import Path

        self.clean.save(Path(folder) / "clean")
        self.corrupted.save(Path(folder) / "corrupted")


def render_pair(
    scene_or_path: Any,
    cameras: Camera | Cameras | Sequence[Camera],
    *,
    config: Any = "morphological",
    seed: int = 0,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    blur_sigma: float = 2.0,
    max_alpha: float = 0.99,
    sh_degree: int | None = None,
    antialiased: bool = False,
) -> Pair:
    """Render a clean/corrupted pair of a scene along `cameras`.

    One load, one perturbation (seeded: the same seed gives the same pair), and both sequences
    rendered in one parallel pass.

    Args:
        scene_or_path: a GaussianScene or a scene file.
        cameras: a Camera, Cameras or a list of cameras sharing one image size.
        config: a preset name ("morphological", "spatial", "radiometric", "naive"), "blur2d",
            a PerturbConfig or its dict.
        seed: perturbation seed.
        background: RGB background in [0, 1].
        blur_sigma: Gaussian sigma in pixels for "blur2d".
        max_alpha, sh_degree, antialiased: render options (see morphgs.rendering.render).

    Returns:
        Pair.

    Raises:
        FileNotFoundError, SceneFormatError: the scene file. ValueError: bad config or cameras.
    """
    import morphgs

    cams = _as_cameras(cameras)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = morphgs.load(scene_or_path) if isinstance(scene_or_path, (str, os.PathLike)) else scene_or_path
    timings["load"] = time.perf_counter() - t0
    corruption = Corruption.make(config, blur_sigma=blur_sigma).for_seed(seed)
    t0 = time.perf_counter()
    corrupted_scene = corruption.corrupt_scene(scene, seed, cams)
    timings["perturb"] = time.perf_counter() - t0
    opts = dict(background=background, max_alpha=max_alpha, sh_degree=sh_degree, antialiased=antialiased)
    t0 = time.perf_counter()
    clean, corrupted = _render_both(scene, corrupted_scene, corruption, cams, **opts)
    timings["render"] = time.perf_counter() - t0
    return Pair(clean, corrupted, corruption.config, int(seed), cams, timings)
