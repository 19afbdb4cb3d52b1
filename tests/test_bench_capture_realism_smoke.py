"""benches/capture_realism.py runs end to end on the committed skull capture: its fits, the real
pair's line, a row per family (matched to the real held-out PSNR, or said unreachable) with the
classifier's AUC and d', and the contact sheet is a real PNG with a column per shown family."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benches" / "capture_realism.py"


def test_capture_realism_matches_each_family_and_writes_the_sheet(tmp_path: Path) -> None:
    pytest.importorskip("torch")  # the two-sample test's network
    sheet = tmp_path / "sheet.png"
    args = [sys.executable, str(BENCH), "--every", "6", "--work", str(tmp_path), "--family", "veil", "--family",
            "morphological", "--family", "popping", "--seeds", "1", "--steps", "10", "--sheet", str(sheet)]
    out = subprocess.run(args, capture_output=True, text=True, check=True, timeout=900).stdout
    assert "skull, every 6th photo (4 training, 20 held out): real sparse fit held out" in out, out
    real = float(out.split("held out ")[1].split(" dB")[0])
    rows = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| ") and "---" not in line}
    for name in ("veil", "morphological"):
        cells = [c.strip() for c in rows[name].split("|")[1:-1]]
        assert abs(float(cells[2]) - real) < 1.0, (name, cells, real)  # matched to the real severity
        auc = float(cells[6])
        assert 0.0 <= auc <= 1.0 and cells[7], cells
    assert "unreachable" in rows["popping"]  # the skull's Gaussians are too small to pop that far
    from morphgs.media import read_image

    img = read_image(sheet)
    # 5 rows (every fourth of 20 held-out views), 4 columns: dense, real, veil, morphological (the
    # frames are the undistorted photos, about 96x64)
    h, w = img.shape[0] // 5, img.shape[1] // 4
    assert img.shape == (5 * h, 4 * w, 3) and 1.3 < w / h < 1.7 and img.std() > 10, img.shape
