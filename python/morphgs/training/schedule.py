"""Learning-rate schedules: linear warmup, then cosine (half a period down to 0), linear decay
or constant — the same factors as diffusers/transformers `get_cosine_schedule_with_warmup`
(num_cycles 0.5) and `get_linear_schedule_with_warmup`, stepped once per optimizer step."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["lr_factor", "make_scheduler"]


def lr_factor(step: int, *, warmup_steps: int, total_steps: int, schedule: str) -> float:
    """The multiplier of the base learning rate for optimizer step `step` (0-based)."""
    if step < warmup_steps:
        return step / max(1, warmup_steps)
    if schedule == "constant":
        return 1.0
    progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
    if schedule == "linear":
        return max(0.0, 1.0 - progress)
    return max(0.0, 0.5 * (1.0 + math.cos(math.pi * progress)))


def make_scheduler(optimizer: Any, *, warmup: float, total_steps: int, schedule: str) -> Any:
    """A LambdaLR over `total_steps` optimizer steps with `round(warmup * total_steps)` warmup steps."""
    import torch

    warmup_steps = int(round(warmup * total_steps))

    def factor(step: int) -> float:
        return lr_factor(step, warmup_steps=warmup_steps, total_steps=total_steps, schedule=schedule)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
