"""The fit's progress bar: tqdm when installed (steps/s and ETA), else a plain stderr line every
few seconds with the same figures."""

from __future__ import annotations

import sys
import time
from typing import Any

__all__ = ["progress_bar"]


class _Plain:
    def __init__(self, total: int, initial: int, enabled: bool, every_s: float = 5.0) -> None:
        self.total, self.n, self.enabled, self.every_s = total, initial, enabled, every_s
        self.t0, self.n0, self.last = time.perf_counter(), initial, 0.0
        self.postfix = ""

    def update(self, k: int) -> None:
        self.n += k
        now = time.perf_counter()
        if self.enabled and (now - self.last >= self.every_s or self.n >= self.total):
            self.last = now
            dt = now - self.t0
            rate = (self.n - self.n0) / dt if dt > 0 else 0.0
            eta = (self.total - self.n) / rate if rate > 0 else float("nan")
            print(f"fit: {self.n}/{self.total} steps, {rate:.2f} steps/s, ETA {eta:.0f} s {self.postfix}",
                  file=sys.stderr)

    def set_postfix_str(self, s: str, refresh: bool = True) -> None:
        self.postfix = s

    def write(self, msg: str) -> None:
        if self.enabled:
            print(msg, file=sys.stderr)

    def close(self) -> None:
        pass


def progress_bar(total: int, initial: int, enabled: bool) -> Any:
    """A bar over `total` steps starting at `initial`."""
    try:
        from tqdm import tqdm
    except ImportError:
        return _Plain(total, initial, enabled)
    return tqdm(total=total, initial=initial, unit="step", desc="fit", file=sys.stderr, disable=not enabled,
                dynamic_ncols=True, smoothing=0.05)
