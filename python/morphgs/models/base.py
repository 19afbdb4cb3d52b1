"""What a refiner is to the training loop, the checkpoints and `morphgs refine`.

A refiner is a `torch.nn.Module` subclassing `Refiner` that owns every part it needs (frozen
encoders, the trainable network, its noise scheduler) and implements a small protocol. The loop
calls only these methods; it never asks which model it runs. docs/training.md ("Adding a model")
is the reference; in short:

- `forward(batch, *, generator)` is the **training objective**: it takes a collated batch (the
  dataset's dict; pixel clips are (B, 3, F, H, W) in [-1, 1]) and returns `(loss, logs)`, the
  scalar loss to back-propagate and a dict of scalar tensors to log. It runs through
  `accelerator.prepare`'s wrapper (DDP, bf16 autocast), so compute losses in float32. All its
  randomness (noise, timesteps) must come from `generator`, which the loop seeds from
  (run seed, step, micro-batch, rank), so a resumed run draws the same noise.
- `param_groups(lr=..., weight_decay=...)`: AdamW parameter groups of the trainable parameters
  (e.g. a widened conv_in with its own learning rate).
- `prepare_data(dataset, *, ctx, accelerator)`: turn the training `PairDataset` into what
  `forward` reads (e.g. VAE-latent and text-embedding caches); it must keep the dataset's keys
  (an index or (index, seed)) and length.
- `refine(corrupted, *, reference, generator)`: inference on one window, (B, 3, F, H, W) in
  [-1, 1] -> same shape in [-1, 1]. `window` is the F it prefers and `size_multiple` the number
  H and W must be divisible by; `morphgs.refine` cuts long clips into overlapping windows, pads
  sizes and blends.
- `save_trained(folder)` / `load_trained(folder)`: write and read back exactly what training
  changed (the default: every parameter with requires_grad, as `trained.safetensors`). A model
  is rebuilt from its config section by its registry `build`, then `load_trained` restores it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from morphgs._core import MorphgsError

__all__ = ["CheckpointError", "ModelContext", "Refiner"]

TRAINED_FILE = "trained.safetensors"


class CheckpointError(MorphgsError):
    """A checkpoint that does not match the model it is loaded into (names the file and keys)."""


@dataclass(frozen=True)
class ModelContext:
    """What a model's `build` knows besides its own config section.

    Attributes:
        frames: F of the training clips (the default refine window).
        size: (H, W) of the training crops, or None.
        reference: clean reference frames per sample (0: the model gets none).
        training: built to train (True) or only to refine (False: skip what only training needs).
        run_dir: the run folder, when there is one.
        cache_dir: where `prepare_data` may keep caches (inside the run folder by default).
    """

    frames: int = 16
    size: tuple[int, int] | None = None
    reference: int = 0
    training: bool = True
    run_dir: Path | None = None
    cache_dir: Path | None = None


class Refiner(torch.nn.Module):
    """Base class of every registered refiner (see the module docstring for the protocol)."""

    #: frames the model refines at once (morphgs.refine's window)
    window: int = 16
    #: H and W must be multiples of this (morphgs.refine pads)
    size_multiple: int = 1

    def forward(self, batch: Mapping[str, Any], *,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The training objective: (scalar loss, {name: scalar tensor} logs)."""
        raise NotImplementedError

    def param_groups(self, *, lr: float, weight_decay: float) -> list[dict[str, Any]]:
        """AdamW parameter groups; the default is one group of every trainable parameter."""
        params = [p for p in self.parameters() if p.requires_grad]
        return [{"params": params, "lr": lr, "weight_decay": weight_decay}]

    def prepare_data(self, dataset: Any, *, ctx: ModelContext, accelerator: Any) -> Any:
        """The training dataset `forward` reads; the default is the pixel dataset unchanged."""
        return dataset

    @torch.no_grad()
    def refine(self, corrupted: torch.Tensor, *, reference: torch.Tensor | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Refine one window: (B, 3, F, H, W) in [-1, 1] -> the same shape in [-1, 1]."""
        raise NotImplementedError

    # ---- what training changed ----
    def trained_state_dict(self) -> dict[str, torch.Tensor]:
        """The tensors training changes: by default every parameter with requires_grad."""
        return {n: p.detach() for n, p in self.named_parameters() if p.requires_grad}

    def save_trained(self, folder: str | os.PathLike[str]) -> None:
        """Write `trained_state_dict()` to `folder/trained.safetensors`."""
        from safetensors.torch import save_file

        Path(folder).mkdir(parents=True, exist_ok=True)
        tensors = {k: v.contiguous().cpu() for k, v in self.trained_state_dict().items()}
        save_file(tensors, str(Path(folder) / TRAINED_FILE), metadata={"format": "pt"})

    def load_trained(self, folder: str | os.PathLike[str]) -> None:
        """Read back what `save_trained` wrote.

        Raises:
            FileNotFoundError: no trained.safetensors. CheckpointError: missing, unexpected or
            mis-shaped tensors (named).
        """
        from safetensors.torch import load_file

        path = Path(folder) / TRAINED_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file (a checkpoint folder holds one)")
        tensors = load_file(str(path))
        expected = self.trained_state_dict()
        missing = sorted(set(expected) - set(tensors))
        unexpected = sorted(set(tensors) - set(expected))
        if missing or unexpected:
            raise CheckpointError(f"{path}: does not fit this model: missing {missing[:5]}, unexpected "
                                  f"{unexpected[:5]} (was it written by another model or config?)")
        for k, v in tensors.items():
            if v.shape != expected[k].shape:
                raise CheckpointError(f"{path}: {k} has shape {tuple(v.shape)}, the model's is "
                                      f"{tuple(expected[k].shape)}")
        self.load_state_dict(tensors, strict=False)
