"""Local model folders: what a diffusers-layout folder must hold, checked before anything loads.

The refiners never touch the Hugging Face hub at run time: every ``from_pretrained`` gets
``local_files_only=True``, and a folder is checked first so that a missing or incomplete one is a
`ModelFolderError` naming the folder and every missing part (rather than a hub lookup, a
download attempt or a stack trace from deep inside diffusers). No torch import here.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from morphgs.diffusion.errors import ModelFolderError

__all__ = [
    "DIFFUSERS",
    "TOKENIZER",
    "TRANSFORMERS",
    "missing_parts",
    "read_json",
    "require_file",
    "require_folder",
    "with_variant",
]

# component kinds: how a subfolder's weights are named
DIFFUSERS = "diffusers"
TRANSFORMERS = "transformers"
TOKENIZER = "tokenizer"

_WEIGHTS = {
    DIFFUSERS: (
        "diffusion_pytorch_model.safetensors",
        "diffusion_pytorch_model.safetensors.index.json",
        "diffusion_pytorch_model.bin",
        "diffusion_pytorch_model.bin.index.json",
    ),
    TRANSFORMERS: (
        "model.safetensors",
        "model.safetensors.index.json",
        "pytorch_model.bin",
        "pytorch_model.bin.index.json",
    ),
}
# any one of these sets makes a loadable tokenizer folder (fast tokenizers, CLIP BPE, sentencepiece)
_TOKENIZER_SETS = (("tokenizer.json",), ("vocab.json", "merges.txt"), ("spiece.model",), ("tokenizer.model",))


def with_variant(name: str, variant: str | None) -> str:
    """A weight file name with diffusers' variant infix (``model.safetensors`` -> ``model.fp16.safetensors``)."""
    if not variant:
        return name
    parts = name.split(".")
    return ".".join(parts[:-1] + [variant] + parts[-1:])


def _component_missing(folder: Path, sub: str, kind: str, variant: str | None) -> list[str]:
    where = folder / sub if sub else folder
    label = f"{sub}/" if sub else ""
    if not where.is_dir():
        return [f"{label} (the whole folder)"] if sub else ["everything (not a folder)"]
    if kind == TOKENIZER:
        if any(all((where / f).is_file() for f in s) for s in _TOKENIZER_SETS):
            return []
        return [f"{label}tokenizer files (tokenizer.json, or vocab.json + merges.txt, or spiece.model)"]
    missing = []
    if not (where / "config.json").is_file():
        missing.append(f"{label}config.json")
    names = [with_variant(n, variant) for n in _WEIGHTS[kind]]
    if not any((where / n).is_file() for n in names):
        missing.append(f"{label}{names[0]} (or {', '.join(names[1:])})")
    return missing


def missing_parts(folder: str | os.PathLike[str], components: Mapping[str, str], *,
                  variant: str | None = None) -> list[str]:
    """What a model folder lacks.

    Args:
        folder: the model folder.
        components: subfolder -> kind (`DIFFUSERS`, `TRANSFORMERS` or `TOKENIZER`); the subfolder
            ``""`` means the folder itself (a lone model such as a motion adapter).
        variant: weight variant (``"fp16"``) the weight files carry, or None.

    Returns:
        Human-readable descriptions of the missing parts, empty when the folder is complete.
    """
    root = Path(folder)
    out: list[str] = []
    for sub, kind in components.items():
        out += _component_missing(root, sub, kind, variant)
    return out


def require_folder(folder: str | os.PathLike[str], components: Mapping[str, str], *, what: str,
                   variant: str | None = None) -> Path:
    """Check a model folder before loading from it.

    Args:
        folder: the model folder.
        components: as in `missing_parts`.
        what: what the folder should be, for messages (``"SD 1.5 model folder"``).
        variant: weight variant, or None.

    Returns:
        The folder as a `Path`.

    Raises:
        FileNotFoundError: the folder does not exist.
        ModelFolderError: it is not a folder, or parts are missing (all of them are named).
    """
    root = Path(folder).expanduser()
    if not root.exists():
        raise FileNotFoundError(f"{what} not found: {root}")
    if not root.is_dir():
        raise ModelFolderError(f"{what} {root}: expected a folder in diffusers layout, found a file")
    missing = missing_parts(root, components, variant=variant)
    if missing:
        raise ModelFolderError(f"{what} {root} is incomplete: missing " + "; ".join(missing))
    return root


def require_file(path: str | os.PathLike[str], *, what: str, suffixes: tuple[str, ...]) -> Path:
    """Check a single-file checkpoint.

    Raises:
        FileNotFoundError: it does not exist.
        ModelFolderError: it is a folder or has another suffix.
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise FileNotFoundError(f"{what} not found: {p}")
    if not p.is_file() or p.suffix.lower() not in suffixes:
        raise ModelFolderError(f"{what} {p}: expected a file ending in {' or '.join(suffixes)}")
    return p


def read_json(path: str | os.PathLike[str], *, what: str) -> dict[str, Any]:
    """Read a JSON object, with errors that name the file.

    Raises:
        FileNotFoundError: the file does not exist.
        ModelFolderError: it is not valid JSON or not an object.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} not found: {p}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ModelFolderError(f"{what} {p}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise ModelFolderError(f"{what} {p}: expected a JSON object, found {type(data).__name__}")
    return data
