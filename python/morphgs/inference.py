"""Refining clips with a trained run: `morphgs refine` and what `morphgs eval` builds on.

- `load_run(RUN)` rebuilds the run's model from `RUN/run.json` through the registry and loads
  the latest (or a given) checkpoint's trained weights.
- `refine_clip(model, frames)` refines a clip of any length: overlapping windows of the model's
  length (`window_plan`), cross-faded linearly over the overlaps so no seam shows, sizes padded
  to the model's multiple, then colour-corrected (Reinhard in CIELAB, `morphgs.color`) against
  the input clip or given reference frames.
- `iter_refined_pairs(RUN, DATA, split="test")` refines the pairs of a curated folder's split
  (the corrupted side) and yields them with their clean and corrupted frames.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from morphgs import media
from morphgs.color import reinhard_transfer
from morphgs.models.base import ModelContext, Refiner
from morphgs.models.registry import create_model

__all__ = ["LoadedRun", "RefinedPair", "iter_refined_pairs", "load_run", "refine_clip", "window_plan"]


@dataclass
class LoadedRun:
    """A run's model, ready to refine."""

    model: Refiner
    config: Any  # morphgs.training.TrainConfig
    checkpoint: Path
    step: int
    device: torch.device


def load_run(run: str | os.PathLike[str], *, checkpoint: str | os.PathLike[str] | None = None,
             device: str | torch.device | None = None) -> LoadedRun:
    """Rebuild a trained model from its run folder.

    Args:
        run: the run folder (`morphgs train --out`).
        checkpoint: a checkpoint folder (default: the run's latest).
        device: where to run (default: CUDA when available, else the CPU).

    Raises:
        FileNotFoundError: no run folder or checkpoint. TrainingError: not a run folder.
        CheckpointError: weights that do not fit the model.
    """
    from morphgs.training.checkpoint import latest_checkpoint
    from morphgs.training.config import TrainConfig
    from morphgs.training.loop import TrainingError, read_run_file

    run_dir = Path(run)
    info = read_run_file(run_dir)
    cfg = TrainConfig.from_dict(info["config"], source=str(run_dir / "run.json"))
    ckpt = Path(checkpoint) if checkpoint is not None else latest_checkpoint(run_dir)
    if ckpt is None:
        raise TrainingError(f"{run_dir}: no checkpoint yet (training writes checkpoints/step-N)")
    if not ckpt.is_dir():
        raise FileNotFoundError(f"{ckpt}: no such checkpoint folder")
    dev = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    ctx = ModelContext(frames=cfg.data.frames, size=cfg.data.size, reference=cfg.data.reference, training=False,
                       run_dir=run_dir, cache_dir=run_dir / "cache")
    model = create_model(cfg.model, cfg.model_config, ctx)
    model.load_trained(ckpt)
    model.eval().to(dev)
    step = int(ckpt.name.split("-")[-1]) if ckpt.name.startswith("step-") else -1
    return LoadedRun(model, cfg, ckpt, step, dev)


def window_plan(n_frames: int, window: int, overlap: int) -> list[tuple[int, np.ndarray]]:
    """Windows covering `n_frames` frames and each window's blend weights.

    Windows start every `window - overlap` frames, the last one aligned to the clip's end. A
    window's weights are 1, except over `overlap` frames at each side it shares with a neighbour,
    where they ramp linearly (1/(overlap+1), 2/(overlap+1), ...) so that neighbours cross-fade.
    The caller divides by the summed weights. A clip shorter than the window is one window
    (the caller pads it).

    Returns:
        [(start, weights of length min(window, n_frames)), ...].

    Raises:
        ValueError: window < 1 or overlap not in [0, window).
    """
    if window < 1 or not 0 <= overlap < window:
        raise ValueError(f"need window >= 1 and 0 <= overlap < window, got window={window}, overlap={overlap}")
    if n_frames <= window:
        return [(0, np.ones(n_frames))]
    stride = window - overlap
    starts = list(range(0, n_frames - window + 1, stride))
    if starts[-1] != n_frames - window:
        starts.append(n_frames - window)
    ramp = np.arange(1, overlap + 1) / (overlap + 1)
    plan = []
    for s in starts:
        w = np.ones(window)
        if s > 0 and overlap:
            w[:overlap] = ramp
        if s + window < n_frames and overlap:
            w[window - overlap:] = ramp[::-1]
        plan.append((s, w))
    return plan


def to_model(frames: np.ndarray, device: torch.device) -> torch.Tensor:
    """(F, H, W, 3) uint8/float [0, 1] -> (1, 3, F, H, W) float32 in [-1, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(frames))
    t = t.float() / 127.5 - 1.0 if t.dtype == torch.uint8 else t.float() * 2.0 - 1.0
    return t.permute(3, 0, 1, 2)[None].to(device)


def _pad_hw(t: torch.Tensor, multiple: int) -> tuple[torch.Tensor, int, int]:
    h, w = t.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        b, c, f = t.shape[:3]
        t = torch.nn.functional.pad(t.reshape(b, c * f, h, w), (0, pw, 0, ph), mode="replicate").reshape(
            b, c, f, h + ph, w + pw)
    return t, h, w


def refine_clip(
    model: Refiner,
    frames: np.ndarray,
    *,
    window: int | None = None,
    overlap: int | None = None,
    reference: np.ndarray | None = None,
    color_correct: bool = True,
    color_reference: np.ndarray | None = None,
    device: str | torch.device | None = None,
    autocast: bool = False,
    generator: torch.Generator | None = None,
) -> np.ndarray:
    """Refine a clip of any length with a model.

    Args:
        model: a Refiner (e.g. `load_run(RUN).model`), in eval mode.
        frames: the corrupted clip, (F, H, W, 3) uint8 or float in [0, 1].
        window: frames per model call (default: the model's `window`).
        overlap: frames shared by neighbouring windows (default: window // 4).
        reference: clean reference frames (R, H, W, 3) for models trained with them.
        color_correct: match the result's CIELAB statistics to `color_reference` (or, if None,
            to the input clip) by Reinhard transfer, as the paper does after inference.
        device: where the model runs (default: where its parameters are).
        autocast: run the model under bf16 autocast.
        generator: for models whose inference draws noise.

    Returns:
        float32 (F, H, W, 3) in [0, 1].

    Raises:
        ValueError: frames that are not an (F, H, W, 3) clip.
    """
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3 or arr.shape[0] < 1:
        raise ValueError(f"frames must be (F, H, W, 3) with F >= 1, got shape {arr.shape}")
    n, h, w, _ = arr.shape
    win = int(window or model.window)
    ov = win // 4 if overlap is None else int(overlap)
    dev = torch.device(device) if device is not None else next(model.parameters()).device
    ref_t = None
    if reference is not None:
        ref_t, _, _ = _pad_hw(to_model(reference, dev), model.size_multiple)
    acc = np.zeros((n, h, w, 3), np.float32)
    total = np.zeros(n, np.float32)
    for start, weights in window_plan(n, win, ov):
        stop = min(start + win, n)
        x, _, _ = _pad_hw(to_model(arr[start:stop], dev), model.size_multiple)
        if x.shape[2] < win:  # a clip shorter than the window: repeat its last frame
            x = torch.cat([x, x[:, :, -1:].expand(-1, -1, win - x.shape[2], -1, -1)], dim=2)
        with torch.no_grad(), torch.autocast(dev.type, dtype=torch.bfloat16, enabled=autocast):
            y = model.refine(x, reference=ref_t, generator=generator)
        y01 = ((y[0, :, : stop - start, :h, :w].float() + 1.0) * 0.5).clamp(0, 1).permute(1, 2, 3, 0).cpu().numpy()
        wts = weights[: stop - start].astype(np.float32)
        acc[start:stop] += y01 * wts[:, None, None, None]
        total[start:stop] += wts
    out = acc / total[:, None, None, None]
    if color_correct:
        out = reinhard_transfer(out, arr if color_reference is None else color_reference)
    return out


@dataclass
class RefinedPair:
    """One refined pair of a curated folder: frames (F, H, W, 3); `refined` is float32 in [0, 1],
    `corrupted` and `clean` are uint8 as read."""

    pair_id: str
    record: Any  # morphgs.data.PairRecord
    refined: np.ndarray
    corrupted: np.ndarray
    clean: np.ndarray


def iter_refined_pairs(
    run: str | os.PathLike[str] | LoadedRun,
    data: str | os.PathLike[str],
    *,
    split: str = "test",
    pairs: Sequence[str] | None = None,
    out: str | os.PathLike[str] | None = None,
    color_correct: bool = True,
    device: str | torch.device | None = None,
    **refine_kwargs: Any,
) -> Iterator[RefinedPair]:
    """Refine the corrupted side of every pair of a curated folder's split (the base of
    `morphgs eval --run RUN --data DIR`).

    Args:
        run: a run folder or a LoadedRun.
        data: the curated folder.
        split: "test", "train" or "all".
        pairs: only these pair ids (default: all of the split).
        out: when given, write each pair's refined frames to `out/<pair_id>/refined/00000.png ...`.
        color_correct, device, refine_kwargs: as `refine_clip` (colour reference: the corrupted clip).

    Yields:
        RefinedPair, in pair-id order.

    Raises:
        FileNotFoundError, DatasetError: as `morphgs.data.load_records`; MediaError reading frames.
    """
    from morphgs.data import DatasetError, load_records

    loaded = run if isinstance(run, LoadedRun) else load_run(run, device=device)
    records = [r for r in load_records(data) if split == "all" or r.split == split]
    if pairs is not None:
        wanted = set(pairs)
        unknown = wanted - {r.pair_id for r in records}
        if unknown:
            raise DatasetError(f"{data}: no pair {sorted(unknown)[0]!r} in split {split!r}")
        records = [r for r in records if r.pair_id in wanted]
    for r in records:
        corrupted = media.read_clip(r.corrupted)
        clean = media.read_clip(r.clean)
        refined = refine_clip(loaded.model, corrupted, color_correct=color_correct, device=loaded.device,
                              **refine_kwargs)
        if out is not None:
            media.write_frames(Path(out) / r.pair_id / "refined", refined)
        yield RefinedPair(r.pair_id, r, refined, corrupted, clean)
