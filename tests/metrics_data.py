"""Real frames for the metric tests: a few small renders of the guitar capture in tests/fixtures
(playcanvas_engine_guitar.compressed.ply, see ATTRIBUTION.md), clean and morphologically perturbed."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import morphgs
from morphgs import trajectory

GUITAR = Path(__file__).resolve().parent / "fixtures" / "playcanvas_engine_guitar.compressed.ply"


@lru_cache(maxsize=4)
def guitar_pair(n_frames: int = 4, width: int = 96, height: int = 64, config: str = "morphological") -> morphgs.Pair:
    """A clean/corrupted render pair of the guitar along a short orbit (cached per process)."""
    scene = morphgs.load(GUITAR)
    cams = trajectory.for_scene(scene, n_frames, resolution=(width, height), arc_degrees=8 * n_frames, margin=0.4)
    return morphgs.render_pair(scene, cams, config=config, seed=1)
