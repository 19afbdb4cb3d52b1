"""benches/fit_bytes.py (the fit-bytes check of speed changes) runs end to end: its dataset, one
fit process per build and thread count, and its verdict, which here (this checkout against its
own package, 1 and 2 threads) must be the same bytes: the fit is deterministic whatever the
thread count."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "fit_bytes.py"


def test_fit_bytes_check_runs_and_finds_the_same_bytes() -> None:
    pkg = BENCH.parents[1] / "python"
    out = subprocess.run([sys.executable, str(BENCH), "--steps", "3", "--threads", "1,2",
                          "--baseline", str(pkg)],
                         capture_output=True, text=True, check=True, timeout=600)
    rows = [r for r in out.stdout.splitlines() if r.startswith("simd=native ")]
    assert len(rows) == 4, out.stdout
    assert len({r.split()[-1] for r in rows}) == 1, out.stdout
    assert "simd=native: same bytes" in out.stdout, out.stdout
