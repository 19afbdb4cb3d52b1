"""Dataset curation: clean/corrupted training pairs from 3DGS scenes at the renderer's speed.

`curate(...)` (also `morphgs curate`), `export_difix(...)` (`morphgs export-difix`) and
`preview(...)` (`morphgs preview`). See docs/curation.md for the layout, the manifest schema,
seeds, resume and scale-out.
"""

from __future__ import annotations

from morphgs.curate.difix import export_difix
from morphgs.curate.manifest import load as load_manifest
from morphgs.curate.plan import ConfigSpec, PairJob, pair_seed, parse_config, scene_split
from morphgs.curate.preview import preview
from morphgs.curate.runner import CurateSummary, curate
from morphgs.curate.sources import SceneSource, builtin_sources, discover

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
