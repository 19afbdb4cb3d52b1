"""`morphgs fit`, `morphgs curate` and `morphgs ablate` read cameras through the same checks
(`morphgs.trajectory.checks`): one bad capture each, one line naming the file and the frame or
record. The issue's two transforms.json cases (a rotation entry of 1e300, one flipped to -1)
fitted "successfully" before."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import morphgs
from capture_helpers import Shot, orbit_poses, pinhole, room, write_colmap, write_transforms

ENV = {**os.environ, "MORPHGS_NUM_THREADS": "1"}


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "morphgs", *args], env=ENV, capture_output=True, text=True,
                          timeout=300)


def _lines(r: subprocess.CompletedProcess[str]) -> list[str]:
    assert "Traceback" not in r.stderr, r.stderr
    return [ln for ln in r.stderr.splitlines() if ln.strip()]


@pytest.mark.parametrize(("entry", "value", "needle"), [
    ((0, 1), 1e300, "beyond 1: not a rotation"),
    ((1, 1), -1.0, "not orthonormal"),
])
def test_fit_refuses_a_transforms_json_rotation_entry_that_is_not_a_rotation(
        entry: tuple[int, int], value: float, needle: str, tmp_path: Path) -> None:
    root = write_transforms(tmp_path / "cap", room(500), [pinhole(w2c, 32, 24) for w2c in orbit_poses(4)])
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][3]["transform_matrix"][entry[0]][entry[1]] = value
    (root / "transforms.json").write_text(json.dumps(meta))
    r = _cli("fit", str(root), "--out", str(tmp_path / "run"), "--steps", "5", "--no-progress")
    assert r.returncode == 1
    lines = _lines(r)
    assert len(lines) == 1 and lines[0].startswith("morphgs fit: error: "), r.stderr
    assert f"{root / 'transforms.json'}: frames[3] (images/frame_00003.png): transform_matrix" in lines[0]
    assert needle in lines[0]
    assert not (tmp_path / "run" / "fit.json").exists()


def _scene_folder(d: Path, bad_focal: bool) -> Path:
    d.mkdir(parents=True)
    morphgs.save(morphgs.synthetic.scene(300, sh_degree=0, seed=1), d / "scene.ply")
    model = write_colmap(d / "sparse" / "0", [Shot(f"im_{i}.png", pinhole(w2c, 32, 24))
                                              for i, w2c in enumerate(orbit_poses(4))], binary=False)
    if bad_focal:  # camera 3 (line 4 of cameras.txt) gets fx = -30
        lines = (model / "cameras.txt").read_text().splitlines()
        parts = lines[3].split()
        parts[4] = "-30"
        lines[3] = " ".join(parts)
        (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    return d


def test_curate_reports_a_colmap_camera_with_a_negative_focal_naming_file_and_line(tmp_path: Path) -> None:
    bad = _scene_folder(tmp_path / "bad", bad_focal=True)
    r = _cli("curate", str(bad), "--out", str(tmp_path / "data"), "-k", "1", "--frames", "2", "--size", "32x24",
             "--no-progress")
    assert r.returncode == 1
    where = f"{bad / 'sparse' / '0' / 'cameras.txt'}:4: camera 3: focal lengths must be positive"
    assert any(where in ln for ln in _lines(r)), r.stderr


def test_ablate_reading_its_scenes_refuses_the_same_camera_in_one_line(tmp_path: Path) -> None:
    good = _scene_folder(tmp_path / "good", bad_focal=False)
    bad = _scene_folder(tmp_path / "bad", bad_focal=True)
    study = tmp_path / "study.toml"
    study.write_text(f'preset = "smoke"\n[scenes]\ninputs = ["{good}", "{bad}"]\n'
                     '[split]\ntrain_ids = ["good"]\ntest_ids = ["bad"]\n[capture]\nsize = [64, 48]\n')
    r = _cli("ablate", "--study", str(study), "--out", str(tmp_path / "study"), "--dry-run")
    assert r.returncode == 1
    lines = _lines(r)
    assert len(lines) == 1, r.stderr
    assert lines[0] == (f"morphgs ablate: error: {bad / 'sparse' / '0' / 'cameras.txt'}:4: camera 3: focal lengths "
                        "must be positive, got fx=-30 fy=27.7128")
