"""The up axis of curate's orbits (issue 20): a z-up scene saved y-down (the loaders' RDF
convention) and curated with the default `--up file` gets the same camera path relative to the
scene, and the same frames, as the z-up scene curated with `--up +z`; the manifest records the
vector; a rerun with another --up is refused; built-in sample scenes keep their +z orbits."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import morphgs
from morphgs import synthetic
from morphgs.camera import Cameras
from morphgs.cli import main
from morphgs.curation import load_manifest
from morphgs.trajectory._rotations import matrix_to_quat, quat_mul

SMALL = ["-k", "2", "--frames", "3", "--size", "48x32", "--no-progress", "--test-fraction", "0"]
# z-up -> RDF (y down): (x, y, z) -> (x, -z, y)
R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _rotated(scene: morphgs.GaussianScene) -> morphgs.GaussianScene:
    q = matrix_to_quat(R)
    quats = np.stack([quat_mul(q, x) for x in np.asarray(scene.quats, np.float64)]).astype(np.float32)
    return morphgs.GaussianScene.from_arrays(
        means=np.ascontiguousarray(np.asarray(scene.means) @ R.T.astype(np.float32)), quats=quats,
        log_scales=scene.log_scales, opacity_logits=scene.opacity_logits, sh0=scene.sh0)


def _c2w(out: Path, pair: str) -> np.ndarray:
    d = json.loads((out / "pairs" / pair / "cameras.json").read_text())
    return np.asarray(Cameras.from_dict(d).camera_to_world, np.float64)


def _frame(out: Path, pair: str, side: str = "clean", i: int = 1) -> np.ndarray:
    with Image.open(out / "pairs" / pair / side / f"{i:05d}.png") as im:
        return np.asarray(im.convert("RGB"), np.float64)


def test_a_y_down_scene_orbits_upright_like_the_z_up_scene_with_up_z(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    base = synthetic.scene(3000, sh_degree=0, seed=1)
    (tmp_path / "zup").mkdir()
    (tmp_path / "ydown").mkdir()
    morphgs.save(base, tmp_path / "zup" / "obj.ply")
    morphgs.save(_rotated(base), tmp_path / "ydown" / "obj.ply")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["curate", str(tmp_path / "ydown" / "obj.ply"), "--out", str(a), *SMALL]) == 0
    assert main(["curate", str(tmp_path / "zup" / "obj.ply"), "--out", str(b), "--up", "+z", *SMALL]) == 0
    ra, rb = load_manifest(a), load_manifest(b)
    assert sorted(ra) == sorted(rb) == ["obj/morphological/0000", "obj/morphological/0001"]
    for pid in ra:
        assert ra[pid]["up"] == [0.0, -1.0, 0.0] and ra[pid]["up_rule"] == "file"
        assert rb[pid]["up"] == [0.0, 0.0, 1.0] and rb[pid]["up_rule"] == "+z"
        ga, gb = _c2w(a, pid), _c2w(b, pid)
        scale = float(np.ptp(np.asarray(base.means), axis=0).max())
        # the same path relative to the scene: positions and orientations agree once rotated back
        np.testing.assert_allclose(ga[:, :3, 3] @ R, gb[:, :3, 3], atol=1e-4 * scale)
        np.testing.assert_allclose(R.T @ ga[:, :3, :3], gb[:, :3, :3], atol=1e-5)
        # ... so the frames show the same picture (float rounding of the rotated Gaussians aside)
        fa, fb = _frame(a, pid), _frame(b, pid)
        assert fb.mean() > 5
        assert np.abs(fa - fb).mean() < 1.0
    # the old +z orbit on the y-down file tumbles: its frames differ from the upright ones
    c = tmp_path / "c"
    assert main(["curate", str(tmp_path / "ydown" / "obj.ply"), "--out", str(c), "--up", "+z", *SMALL]) == 0
    assert np.abs(_frame(c, "obj/morphological/0001") - _frame(b, "obj/morphological/0001")).mean() > 5
    # another --up into a folder curated with the default is refused in one line, not reused
    capsys.readouterr()
    assert main(["curate", str(tmp_path / "ydown" / "obj.ply"), "--out", str(a), "--up", "+z", *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("morphgs curate: error:") and "/up)" in err[0]
    # the same up spelled as a vector resumes (nothing to redo)
    assert main(["curate", str(tmp_path / "ydown" / "obj.ply"), "--out", str(a), "--up", "0,-2,0", *SMALL]) == 0
    assert "0 pairs made, 2 already done" in capsys.readouterr().err


def test_a_bad_up_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["curate", "--out", str(tmp_path / "x"), "--up", "sideways", *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("morphgs curate: error: --up:") and "sideways" in err[0]
    assert not (tmp_path / "x" / "pairs").exists()


def test_builtin_sample_scenes_keep_their_z_up_orbits_whatever_up_says(tmp_path: Path) -> None:
    args = ["--sample-gaussians", "1500", "-k", "2", "--frames", "2", "--size", "40x24", "--no-progress"]
    assert main(["curate", "--out", str(tmp_path / "default"), *args]) == 0
    assert main(["curate", "--out", str(tmp_path / "x"), "--up=-x", *args]) == 0

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / "pairs").rglob("*")) if p.is_file()}

    assert files(tmp_path / "default") == files(tmp_path / "x")
    recs = load_manifest(tmp_path / "default")
    assert recs and all(r["up"] == [0.0, 0.0, 1.0] and r["up_rule"] == "builtin" for r in recs.values())
