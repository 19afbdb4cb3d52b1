"""benches/capture_anatomy.py runs end to end on the committed skull capture: its two fits, the
group table, the geometry/colour swap and the residual line, and the contact sheet is a real PNG;
a second run resumes the fits and prints the same figures."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1] / "benches" / "capture_anatomy.py"


def test_capture_anatomy_runs_and_resumes(tmp_path: Path) -> None:
    has_torch = importlib.util.find_spec("torch") is not None  # the hidden-Gaussian row needs it
    args = [sys.executable, str(BENCH), "--every", "6", "--work", str(tmp_path)]
    first = subprocess.run(args, capture_output=True, text=True, check=True, timeout=900).stdout
    for row in ("skull: 24 photos, training [0, 6, 12, 18] (4), 20 held out", "held-out PSNR: sparse vs photo",
                "| seen by 3+ |", "| the sparse geometry, the dense fit's colours |", "of the squared error on the object",
                "contact sheet"):
        assert row in first, first
    assert ("| hidden in every training view" in first) == has_torch
    from morphgs.media import read_image

    sheet = read_image(tmp_path / "sheet-every6.png")
    assert sheet.ndim == 3 and sheet.shape[2] == 3 and sheet.std() > 10
    again = subprocess.run(args, capture_output=True, text=True, check=True, timeout=900).stdout
    assert again == first
    assert np.isfinite(float(first.split("sparse vs photo ")[1].split(" dB")[0]))
