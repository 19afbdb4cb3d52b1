"""What every export shares: its summary, captions, the `export.json` provenance file, progress."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs.exports.source import SPLITS, ExportError, PairEntry

__all__ = ["DEFAULT_PROMPT", "ExportSummary", "Captions", "load_captions", "progress_bar", "write_export_json",
           "write_json"]

DEFAULT_PROMPT = "remove degradation"


@dataclass
class ExportSummary:
    """What an export wrote: `counts` pairs per split into `out`, and the warnings it gave."""

    format: str
    out: Path
    counts: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def text(self) -> str:
        parts = ", ".join(f"{self.counts.get(s, 0)} {s}" for s in SPLITS)
        return f"morphgs export {self.format}: {parts} pairs -> {self.out}"


class Captions:
    """The text of each pair: `captions[pair_id]`, else `captions[scene]`, else the prompt."""

    def __init__(self, prompt: str = DEFAULT_PROMPT, captions: Mapping[str, str] | None = None) -> None:
        if not prompt.strip():
            raise ExportError("the prompt is empty: trainers read an empty CSV cell as a missing value")
        self.prompt, self.captions = prompt, dict(captions or {})

    def __call__(self, entry: PairEntry) -> str:
        scene = str(entry.record.get("scene", ""))
        return self.captions.get(entry.pair_id, self.captions.get(scene, self.prompt))


def load_captions(path: str | os.PathLike[str]) -> dict[str, str]:
    """A captions file: one JSON object mapping pair ids or scene ids to text.

    Raises:
        FileNotFoundError: no such file. ExportError: not JSON, or not an object of strings.
    """
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no such captions file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ExportError(f"{p}: captions file is not JSON ({e})") from None
    if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
        raise ExportError(f"{p}: captions must be one JSON object of \"pair id or scene\": \"text\"")
    return data


def write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def write_export_json(out: Path, *, fmt: str, source: Path, entries: Sequence[PairEntry],
                      options: dict[str, Any], warnings: Sequence[str]) -> dict[str, int]:
    """`OUT/export.json`: format, source folder, options, counts per split, and key -> pair id."""
    import morphgs

    counts = {s: sum(1 for e in entries if e.split == s) for s in SPLITS}
    write_json(out / "export.json", {
        "format": fmt,
        "morphgs_version": morphgs.__version__,
        "source": str(source),
        "options": options,
        "counts": counts,
        "warnings": list(warnings),
        "pairs": [{"key": e.key, "pair_id": e.pair_id, "split": e.split, "frames": e.frames,
                   "resolution": [e.width, e.height]} for e in entries],
    })
    return counts


def progress_bar(total: int, *, enabled: bool, unit: str) -> Any:
    """A tqdm bar on stderr (or one line per step without tqdm), as `morphgs curate` shows."""
    from morphgs.curation import runner

    return runner.progress_bar(total, enabled, desc="export", unit=unit)
