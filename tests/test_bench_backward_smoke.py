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


def test_bench_backward_ab_mode_runs() -> None:
    """--baseline runs the alternating A/B (here against this checkout's own package) and
    prints each round and the ratios."""
    pkg = BENCH.parents[1] / "python"
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--baseline", str(pkg),
                          "--rounds", "1"],
                         capture_output=True, text=True, check=True, timeout=600)
    for row in ("backward A/B", "baseline 0", "this 0", "median bwd_cpu", "this/baseline",
                "backward evaluations"):
        assert row in out.stdout, out.stdout
