"""Dataset curation: clean/corrupted training pairs from 3DGS scenes at the renderer's speed.

`curate(...)` (also `morphgs curate`), `export_difix(...)` (`morphgs export-difix`) and
`preview(...)` (`morphgs preview`). See docs/curation.md for the layout, the manifest schema,
seeds, resume and scale-out.
"""

from __future__ import annotations

from morphgs.curation.difix import export_difix
from morphgs.curation.manifest import load as load_manifest
from morphgs.curation.plan import ConfigSpec, PairJob, pair_seed, parse_config, scene_split
from morphgs.curation.preview import preview
from morphgs.curation.runner import CurateSummary, curate
from morphgs.curation.sources import SceneSource, builtin_sources, discover

__all__ = [
    "ConfigSpec",
    "CurateSummary",
    "PairJob",
    "SceneSource",
    "builtin_sources",
    "curate",
    "discover",
    "export_difix",
    "load_manifest",
    "pair_seed",
    "parse_config",
    "preview",
    "scene_split",
]
