"""`morphgs fit DATA... --out ROOT`: one run per capture in worker processes, resumable per
capture, going on past a failed capture (reported at the end), and `morphgs curate` reading the
output root as it is."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from capture_helpers import Shot, orbit_poses, pinhole, room, write_capture, write_transforms
from fit_helpers import small_config
from morphgs.fit import FitConfig


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "morphgs.cli", *args], capture_output=True, text=True)


def test_many_captures_fit_resume_report_failures_and_feed_curate(tmp_path: Path) -> None:
    scene = room(2000)
    caps = tmp_path / "captures"
    write_transforms(caps / "kitchen", scene, [pinhole(w2c, 32, 24) for w2c in orbit_poses(6)])
    shots = [Shot(f"im_{i}.png", pinhole(w2c, 32 + (i % 2), 24)) for i, w2c in enumerate(orbit_poses(6))]
    write_capture(caps / "garden", scene, shots)
    (caps / "broken").mkdir()
    (caps / "broken" / "transforms.json").write_text("{not json")
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(FitConfig.from_dict(small_config(10)).to_toml())
    root = tmp_path / "runs"
    r = _cli("fit", str(caps / "*"), "--out", str(root), "--config", str(cfg), "--workers", "2", "--no-progress")
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()
    assert "2 of 3 captures fitted" in r.stderr and any("failed: broken" in ln and "not valid JSON" in ln for ln in last)
    recs = {s["scene"]: s for s in json.loads((root / "fits.json").read_text())["scenes"]}
    assert recs["broken"]["status"] == "failed" and recs["garden"]["status"] == recs["kitchen"]["status"] == "done"
    for name in ("garden", "kitchen"):
        assert (root / name / "fit.json").is_file()
    stamp = (root / "garden" / "fit.json").stat().st_mtime_ns
    # rerun: finished captures are skipped, the broken one is tried again and still reported
    r2 = _cli("fit", str(caps / "garden"), str(caps / "kitchen"), "--out", str(root), "--config", str(cfg),
              "--no-progress")
    assert r2.returncode == 0, r2.stderr
    assert (root / "garden" / "fit.json").stat().st_mtime_ns == stamp
    # the output root is what curate reads: each run folder is a scene with its cameras
    r3 = _cli("curate", str(root / "garden"), str(root / "kitchen"), "--out", str(tmp_path / "data"), "-k", "1",
              "--frames", "2", "--size", "32x24", "--no-progress")
    assert r3.returncode == 0, r3.stderr
    man = [json.loads(ln) for ln in (tmp_path / "data" / "manifest.jsonl").read_text().splitlines() if ln.strip()]
    assert sorted({m["scene"] for m in man}) == ["garden", "kitchen"]


def test_a_glob_that_matches_nothing_is_a_one_line_error(tmp_path: Path) -> None:
    r = _cli("fit", str(tmp_path / "nothing-*"), "--out", str(tmp_path / "runs"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "no capture matches" in r.stderr
