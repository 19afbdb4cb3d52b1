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


def test_bench_fit_baseline_ab_runs_and_rejects_a_folder_without_morphgs(tmp_path: Path) -> None:
    # this build as its own baseline: the A/B table and its ratios are printed
    python_dir = BENCH.parents[1] / "python"
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--only", "garden", "--baseline", str(python_dir),
                          "--rounds", "1", "--dir", str(tmp_path)], capture_output=True, text=True, check=True,
                         timeout=600)
    for row in ("## garden A/B, 2 threads, 1 rounds", "baseline median", "this median", "this / baseline: step"):
        assert row in out.stdout, out.stdout
    bad = subprocess.run([sys.executable, str(BENCH), "--quick", "--only", "garden", "--baseline", str(tmp_path),
                          "--dir", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0
    assert "holds no morphgs package" in bad.stderr
