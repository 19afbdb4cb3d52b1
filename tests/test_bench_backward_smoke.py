"""benches/bench_backward.py --quick runs end to end (its worker subprocesses per thread count
and kernel, and the comparison with gsplat's torch reference) and prints its table."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_backward.py"


def test_bench_backward_quick_runs() -> None:
    pytest.importorskip("torch")
    pytest.importorskip("gsplat")
    out = subprocess.run([sys.executable, str(BENCH), "--quick"],
                         capture_output=True, text=True, check=True, timeout=600)
    for row in ("garden 162x105", "scalar kernel", "morphgs.torch.rasterization", "x faster"):
        assert row in out.stdout, out.stdout
