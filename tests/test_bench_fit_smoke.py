"""benches/bench_fit.py --quick still runs every section end to end and prints its tables."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_fit.py"


def test_bench_fit_quick_runs(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--dir", str(tmp_path)],
                         capture_output=True, text=True, check=True, timeout=600)
    for row in ("## garden 648x420", "held-out PSNR", "## sparse-view fits", "S_8", "OpenSplat -n 300, cited"):
        assert row in out.stdout, out.stdout
    assert list(tmp_path.iterdir()) == []  # its scratch folder is removed
