"""benches/bench_ply.py --quick still runs end to end (it checks morphgs against the plyfile path
before timing) and prints its table."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_ply.py"


def test_bench_ply_quick_runs(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--dir", str(tmp_path)],
                         capture_output=True, text=True, check=True, timeout=300)
    for row in ("morphgs.load", "plyfile + numpy conversion", "np.fromfile (bare read)",
                "morphgs.save_ply", "speed-up over plyfile", "peak memory / array bytes"):
        assert row in out.stdout, out.stdout
    assert list(tmp_path.iterdir()) == []  # its temporary folder is cleaned up
