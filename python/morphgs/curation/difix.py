"""Export a curated dataset as Difix3D's `data.json`.

Difix3D's `PairedDataset` (src/dataset.py in nv-tlabs/Difix3D) reads `json.load(f)[split]` for
split "train" or "test", and for every id the keys "image" (the degraded input), "target_image"
(the clean target), "ref_image" (optional clean reference view) and "prompt", opening the image
paths as given. One entry per frame of every PNG pair: image = corrupted frame, target_image =
the clean frame, ref_image = the clean frame half a clip away (a nearby clean view, as Difix's
reference views are).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsError
from morphgs.curation import manifest

__all__ = ["export_difix"]

DEFAULT_PROMPT = "remove degradation"


def export_difix(
    dataset: str | os.PathLike[str],
    out_json: str | os.PathLike[str],
    *,
    prompt: str = DEFAULT_PROMPT,
    relative: bool = False,
    configs: list[str] | None = None,
    ref_offset: int | None = None,
) -> dict[str, int]:
    """Write Difix3D's data.json for the PNG pairs of a curated folder.

    Args:
        dataset: the curate output folder (holding manifest*.jsonl).
        out_json: the JSON file to write.
        prompt: the text prompt of every entry.
        relative: paths relative to the JSON file's folder (absolute by default, which is what
            Difix3D's loader opens without a root).
        configs: only pairs of these config names (all by default).
        ref_offset: frames between an entry and its reference frame (default: half the clip).

    Returns:
        Entry counts per split.

    Raises:
        MorphgsError: no pairs, or pairs written as video (Difix reads frames).
    """
    root = Path(dataset).resolve()
    recs = manifest.load(root)
    if configs:
        recs = {k: r for k, r in recs.items() if r.get("config_name") in configs}
    if not recs:
        raise MorphgsError(f"{root}: no finished pairs in manifest*.jsonl")
    out_path = Path(out_json).resolve()
    base = out_path.parent

    def ref(p: Path) -> str:
        return os.path.relpath(p, base) if relative else str(p)

    data: dict[str, dict[str, Any]] = {"train": {}, "test": {}}
    for pid in sorted(recs):
        r = recs[pid]
        if r.get("video"):
            raise MorphgsError(f"{root}: pair {pid} was written as video; Difix3D reads frames "
                               "(curate without --video)")
        n = int(r["frames"])
        off = (n // 2 if ref_offset is None else int(ref_offset)) % n if n > 1 else 0
        split = "test" if r.get("split") == "test" else "train"
        clean, corrupted = root / r["paths"]["clean"], root / r["paths"]["corrupted"]
        stem = pid.replace("/", "_")
        for i in range(n):
            data[split][f"{stem}_{i:05d}"] = {
                "image": ref(corrupted / f"{i:05d}.png"),
                "target_image": ref(clean / f"{i:05d}.png"),
                "ref_image": ref(clean / f"{(i + off) % n:05d}.png"),
                "prompt": prompt,
            }
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(out_path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, out_path)
    return {k: len(v) for k, v in data.items()}
