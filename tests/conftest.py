"""Shared fixtures. Real scene files come from tests/fixtures in this repository (see its ATTRIBUTION.md)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# no test may reach the Hugging Face hub: set before anything imports huggingface_hub (which
# reads it once), so an accidental from_pretrained of a hub id fails fast
os.environ.setdefault("HF_HUB_OFFLINE", "1")

REPO = Path(__file__).resolve().parents[1]
FIXTURES = Path(os.environ.get("MORPHGS_FIXTURES", REPO / "tests" / "fixtures"))


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    if not FIXTURES.is_dir():
        pytest.fail(f"fixtures not found at {FIXTURES} (they ship in tests/fixtures; MORPHGS_FIXTURES overrides)")
    return FIXTURES


def _curated(root: Path, **kwargs: object) -> Path:
    """A tiny curated folder of the two built-in sample scenes (3000 Gaussians each), one scene in
    each split (the split seed is picked so), made with `morphgs.curate`."""
    import morphgs
    from morphgs.curation import scene_split

    seed = next(s for s in range(100) if {scene_split(f"sample-{i}", test_fraction=0.5, split_seed=s)
                                          for i in (0, 1)} == {"train", "test"})
    args: dict = dict(configs=("morphological",), pairs_per_scene=2, frames=5, resolution=(64, 48),
                      test_fraction=0.5, split_seed=seed, builtin_gaussians=3000, progress=False,
                      log=lambda m: None)
    args.update(kwargs)
    summary = morphgs.curate(out=root, **args)
    assert summary.ok and summary.done == summary.planned > 0
    return root


@pytest.fixture(scope="session")
def curated_frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """PNG pairs with depth: 2 scenes x 2 pairs, 5 frames (4k+1) of 64x48 (divisible by 16)."""
    return _curated(tmp_path_factory.mktemp("curated") / "frames", depth=True)


@pytest.fixture(scope="session")
def curated_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same scenes curated with --video: one MP4 per side, 1 pair per scene."""
    return _curated(tmp_path_factory.mktemp("curated") / "video", video=True, pairs_per_scene=1)


@pytest.fixture(scope="session")
def curated_odd(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Shapes the video trainers do not want: 4 frames of 33x25 (odd sides, not divisible by 16)."""
    return _curated(tmp_path_factory.mktemp("curated") / "odd", frames=4, resolution=(33, 25), pairs_per_scene=1)
