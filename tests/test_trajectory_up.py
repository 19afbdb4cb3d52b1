"""The up axis of scenes without cameras: a z-up scene turned into the loaders' RDF convention
(y down) and saved as PLY, glTF (+Y up on disk), spz (RUB on disk) and .splat comes back in RDF
axes from every format, and an orbit with the file convention's up frames it exactly as the
z-up orbit frames the original; the old +z default tumbles it. Also the scene-based rule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import synthetic, trajectory
from morphgs.trajectory._rotations import matrix_to_quat, quat_mul

# z-up -> RDF (y down): (x, y, z) -> (x, -z, y)
R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _rotated(scene: morphgs.GaussianScene) -> morphgs.GaussianScene:
    q = matrix_to_quat(R)
    quats = np.stack([quat_mul(q, x) for x in np.asarray(scene.quats, np.float64)]).astype(np.float32)
    return morphgs.GaussianScene.from_arrays(
        means=np.ascontiguousarray(np.asarray(scene.means) @ R.T.astype(np.float32)), quats=quats,
        log_scales=scene.log_scales, opacity_logits=scene.opacity_logits, sh0=scene.sh0)


def _orbit(scene, up):  # type: ignore[no-untyped-def]
    return trajectory.for_scene(scene, 6, resolution=(64, 48), up=up, arc_degrees=300.0)


@pytest.mark.parametrize("ext", [".ply", ".glb", ".spz", ".splat"])
def test_each_format_comes_back_y_down_and_the_orbit_matches_the_scene(tmp_path: Path, ext: str) -> None:
    base = synthetic.scene(3000, sh_degree=0, seed=1)
    path = tmp_path / f"scene{ext}"
    morphgs.save(_rotated(base), path)
    loaded = morphgs.load(path)
    up, why = trajectory.scene_up(loaded, "file")
    assert "RDF" in why
    np.testing.assert_allclose(_orbit(loaded, "file").camera_to_world, _orbit(loaded, up).camera_to_world)
    want = _orbit(base, (0, 0, 1)).camera_to_world
    got = _orbit(loaded, up).camera_to_world
    tol = 2e-2 * float(np.ptp(np.asarray(base.means), axis=0).max())  # spz / .splat quantise positions
    np.testing.assert_allclose(got[:, :3, 3] @ R, want[:, :3, 3], atol=tol)  # positions, back in z-up
    np.testing.assert_allclose(R.T @ got[:, :3, :3], want[:, :3, :3], atol=2e-2)  # orientations: no tumble
    # the old default (+z) on a y-down scene: the cameras' image-up is not the scene's up
    bad = _orbit(loaded, (0, 0, 1)).camera_to_world
    assert not np.allclose(R.T @ bad[:, :3, :3], want[:, :3, :3], atol=0.2)


def test_scene_rule_finds_the_ground_and_parse_up() -> None:
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-5, 5, (3000, 2)), rng.normal(0, 0.05, 3000)]
    things = np.c_[rng.uniform(-1, 1, (600, 2)), rng.uniform(0, 2, 600)]
    pts = np.vstack([ground, things])
    up, _ = trajectory.scene_up(pts, "scene")
    np.testing.assert_allclose(up, [0, 0, 1], atol=0.05)
    up2, _ = trajectory.scene_up(pts @ R.T, "scene")
    np.testing.assert_allclose(up2, [0, -1, 0], atol=0.05)
    np.testing.assert_allclose(trajectory.parse_up("-y"), [0, -1, 0])
    np.testing.assert_allclose(trajectory.parse_up("0,0,2"), [0, 0, 1])
    with pytest.raises(ValueError, match="expected"):
        trajectory.parse_up("up")
