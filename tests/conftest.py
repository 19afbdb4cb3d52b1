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
