"""benches/bench_formats.py --quick runs end to end: it checks morphgs against its NumPy decoders
(compressed PLY and .spz) before timing, exits non-zero if they disagree, and prints its table."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_formats.py"


def test_bench_formats_quick_runs_and_decoders_agree() -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--quick"],
                         capture_output=True, text=True, check=True, timeout=300)
    for row in ("playcanvas_engine_test.compressed.ply", "(.spz v3)", "numpy/morphgs",
                "playcanvas_engine_monkey_0001.sog", "(.glb)", "(SceneSplat .npy)",
                ".spz v4", ".compressed.ply"):
        assert row in out.stdout, out.stdout
