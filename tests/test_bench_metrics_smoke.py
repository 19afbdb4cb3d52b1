"""benches/bench_metrics.py --quick runs end to end: it checks our SSIM against torchmetrics' on
the benchmark clip (exits non-zero if they disagree) and prints its table."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_metrics.py"


def test_bench_metrics_quick_runs_and_ssim_agrees_with_torchmetrics() -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--no-vgg"],
                         capture_output=True, text=True, check=True, timeout=600)
    for row in ("| psnr |", "| ssim, torchmetrics (reference) |", "| lpips alex |", "E_flow + E_warp", "clips/s"):
        assert row in out.stdout, out.stdout
