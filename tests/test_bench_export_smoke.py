"""benches/bench_export.py --quick runs end to end: it curates a tiny folder, exports it in every
format and prints one row per format."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_export.py"


def test_bench_export_quick_runs_every_format() -> None:
    out = subprocess.run([sys.executable, "-W", "error", str(BENCH), "--quick"],
                         capture_output=True, text=True, check=True, timeout=300)
    for row in ("diffsynth, workers=1", "videox-fun", "thedenk", "webdataset + float16 depth", "difix"):
        assert row in out.stdout, out.stdout
