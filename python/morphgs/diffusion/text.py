"""Prompts: one default prompt or per-pair captions from a file, encoded once for the cache.

- CLIP (SD 1.5): padded to the tokenizer's ``model_max_length`` (77), ``last_hidden_state``.
- UMT5 (Wan): padded to ``max_length`` (512 in the Wan pipelines) with the attention mask, the
  embeddings past each prompt's length set to zero, as `WanPipeline._get_t5_prompt_embeds` does.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from morphgs._core import MorphgsError

__all__ = ["DEFAULT_PROMPT", "encode_prompts", "load_captions"]

DEFAULT_PROMPT = "remove degradation"


def load_captions(path: str | os.PathLike[str]) -> dict[str, str]:
    """Per-pair captions from a file.

    Args:
        path: a JSON object ``{pair_id: caption}``, or JSON lines ``{"pair_id": ..., "caption": ...}``.

    Returns:
        pair_id -> caption.

    Raises:
        FileNotFoundError: the file does not exist.
        MorphgsError: a line or entry is malformed (the file and line are named).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"captions file not found: {p}") from None
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise MorphgsError(f"captions file {p}: not valid JSON ({e})") from None
        if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise MorphgsError(f"captions file {p}: expected an object mapping pair ids to caption strings")
        return dict(data)
    out: dict[str, str] = {}
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as e:
            raise MorphgsError(f"captions file {p} line {i}: not valid JSON ({e})") from None
        if not (isinstance(rec, dict) and isinstance(rec.get("pair_id"), str) and isinstance(rec.get("caption"), str)):
            raise MorphgsError(f"captions file {p} line {i}: expected {{\"pair_id\": str, \"caption\": str}}")
        out[rec["pair_id"]] = rec["caption"]
    return out


@torch.no_grad()
def encode_prompts(tokenizer: Any, text_encoder: Any, prompts: Sequence[str], *,
                   max_length: int | None = None, masked: bool = False) -> torch.Tensor:
    """Encode prompts with a frozen text encoder.

    Args:
        tokenizer: the model's tokenizer.
        text_encoder: `CLIPTextModel` or `UMT5EncoderModel` (anything returning ``last_hidden_state``).
        prompts: the prompts.
        max_length: padded length; None uses the tokenizer's ``model_max_length``.
        masked: pass the attention mask and zero the embeddings past each prompt (Wan/UMT5).

    Returns:
        float32 (len(prompts), max_length, hidden).
    """
    length = int(max_length or tokenizer.model_max_length)
    tok = tokenizer([" ".join(p.split()) for p in prompts], padding="max_length", max_length=length,
                    truncation=True, return_attention_mask=True, return_tensors="pt")
    device = next(text_encoder.parameters()).device
    ids, mask = tok.input_ids.to(device), tok.attention_mask.to(device)
    if not masked:
        return text_encoder(ids).last_hidden_state.float().cpu()
    out = text_encoder(ids, attention_mask=mask).last_hidden_state.float()
    return (out * mask.unsqueeze(-1).to(out.dtype)).cpu()
