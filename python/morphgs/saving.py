"""`morphgs.save`: write a scene in the format its file name asks for."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from morphgs._core import (
    GaussianScene,
    MorphgsWarning,
    save_compressed_ply,
    save_glb,
    save_ply,
    save_splat,
    save_spz,
)

#: Output suffixes (matched case-insensitively, longest first) and what writes them.
WRITERS: dict[str, str] = {
    ".compressed.ply": "SuperSplat compressed PLY (quantised, Morton-ordered, SH up to degree 3)",
    ".ply": "INRIA 3DGS PLY (float32, all SH bands)",
    ".splat": "antimatter15 .splat (32 bytes per Gaussian, no SH bands)",
    ".spz": "Niantic .spz (v3 gzip by default, v4 zstd with spz_version=4; RUB axes)",
    ".glb": "glTF binary with KHR_gaussian_splatting (activated values, +Y up, SH up to degree 3)",
}


def format_for(path: str | Path) -> str:
    """The writer suffix for `path` (one of `WRITERS`).

    Args:
        path: an output file name.

    Returns:
        The matching key of `WRITERS`, e.g. ".compressed.ply".

    Raises:
        ValueError: no writer handles the name's suffix.
    """
    name = Path(path).name.lower()
    for suffix in sorted(WRITERS, key=len, reverse=True):
        if name.endswith(suffix):
            return suffix
    raise ValueError(
        f"{path}: unknown output extension {Path(path).suffix.lower()!r}; expected one of "
        + ", ".join(sorted(WRITERS))
    )


def _warn_dropped_bands(scene: GaussianScene, path: str | Path, what: str, keep: int) -> None:
    if scene.sh_degree > keep:
        warnings.warn(
            f"{path}: {what} holds SH up to degree {keep}; the scene's degree-{scene.sh_degree} "
            f"bands above {keep} are dropped",
            MorphgsWarning,
            stacklevel=3,
        )


def save(scene: GaussianScene, path: str | Path, *, spz_version: int = 3, **options: Any) -> None:
    """Write `scene` to `path` in the format named by its suffix (see `WRITERS`).

    Args:
        scene: the scene, in PLY/OpenCV (RDF) axes.
        path: the output file; `.compressed.ply`, `.ply`, `.splat`, `.spz` or `.glb`.
        spz_version: 3 (gzip, read by every .spz viewer) or 4 (zstd streams) for `.spz`.
        **options: passed to the writer (e.g. `spz_axes="stored"` for `.spz`).

    Raises:
        ValueError: unknown suffix, a scene holding NaN/Inf, or a bad option value.
        OSError: the file cannot be written.
    """
    fmt = format_for(path)
    if fmt == ".compressed.ply":
        _warn_dropped_bands(scene, path, "a compressed PLY", 3)
        save_compressed_ply(scene, path, **options)
    elif fmt == ".ply":
        save_ply(scene, path, **options)
    elif fmt == ".splat":
        save_splat(scene, path, **options)
    elif fmt == ".spz":
        save_spz(scene, path, version=spz_version, **options)
    else:
        _warn_dropped_bands(scene, path, "KHR_gaussian_splatting", 3)
        save_glb(scene, path, **options)
