"""Random initialisation where the scene is: points along the training rays (morphgs.fit.rays),
the forward-facing warning, and the fit it rescues (an LLFF-style capture that a box of random
points around the cameras turns into a haze)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from capture_helpers import forward_facing_cameras, orbit_poses, pinhole, room, write_transforms
from fit_helpers import small_config
from morphgs import MorphgsWarning
from morphgs.fit import fit
from morphgs.fit.init import camera_box
from morphgs.fit.rays import depth_range, looks_forward_facing, ray_points
from morphgs.fit.run import scene_scale_of


def _in_frustum(cams, pts):  # type: ignore[no-untyped-def]
    seen = np.zeros(len(pts), bool)
    for c in cams:
        z = (pts @ c.world_to_camera[:3, :3].T + c.world_to_camera[:3, 3])[:, 2]
        uv = c.project(pts)
        seen |= (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= c.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= c.height)
    return seen


def test_ray_points_lie_in_the_training_frustums_where_a_box_does_not() -> None:
    cams = forward_facing_cameras()
    assert looks_forward_facing(cams)
    imgs = [np.full((c.height, c.width, 3), 100, np.uint8) for c in cams]
    s = scene_scale_of(cams)
    pts, cols, desc = ray_points(cams, imgs, 4000, 3, s)
    assert _in_frustum(cams, pts.astype(np.float64)).all()
    np.testing.assert_allclose(cols, 100 / 255, atol=1e-6)
    near, far, _ = depth_range(cams, s)
    lo, hi = camera_box(np.stack([c.center for c in cams]), s)
    box = np.random.default_rng(0).uniform(lo, hi, size=(4000, 3))
    assert _in_frustum(cams, box).mean() < 0.6  # half the box is behind or beside the cameras
    again, _, _ = ray_points(cams, imgs, 4000, 3, s)
    assert again.tobytes() == pts.tobytes()  # seeded
    assert ray_points(cams, imgs, 4000, 4, s)[0].tobytes() != pts.tobytes()


def test_an_orbit_converges_and_is_not_forward_facing() -> None:
    cams = [pinhole(w2c, 32, 24) for w2c in orbit_poses(12)]
    assert not looks_forward_facing(cams)
    from morphgs import synthetic

    o = synthetic.suggested_orbit()
    near, far, how = depth_range(cams, scene_scale_of(cams))
    d = float(np.linalg.norm(cams[0].center - np.asarray(o.center)))
    assert "converge" in how and near == pytest.approx(d / 2, rel=1e-6) and far == pytest.approx(3 * d, rel=1e-6)


def test_forward_facing_capture_warns_and_ray_init_beats_the_box(tmp_path: Path) -> None:
    scene = room(8000)
    root = write_transforms(tmp_path / "ff", scene, forward_facing_cameras())
    cfg = small_config(300, output={"eval_every": 0, "checkpoint_every": 1000, "preview_every": 0,
                                    "progress_every": 0.0, "lpips": "off"})
    with pytest.warns(MorphgsWarning, match="forward-facing"):
        rays = fit(root, tmp_path / "rays", config=cfg, init="random", progress=False)
    with pytest.warns(MorphgsWarning, match="forward-facing"):
        box = fit(root, tmp_path / "box", config=cfg, init="box", progress=False)
    assert "along the training rays" in json.loads((tmp_path / "rays" / "fit.json").read_text())["init"]
    assert rays.heldout_psnr is not None and box.heldout_psnr is not None
    assert rays.heldout_psnr > box.heldout_psnr + 5.0, (rays.heldout_psnr, box.heldout_psnr)


def test_sparse_fits_that_start_from_random_points_on_purpose_do_not_ask_for_sfm_points(tmp_path: Path) -> None:
    """curate's and ablate's sparse fits start from random points by design (SfM points come
    from every view): inside `random_init_on_purpose` the forward-facing hint is not shown,
    other warnings still are, and outside it the hint is back."""
    import warnings

    from morphgs.fit.run import random_init_on_purpose

    root = write_transforms(tmp_path / "ff", room(2000), forward_facing_cameras((32, 24), (3, 2)))
    cfg = small_config(5, output={"eval_every": 0, "checkpoint_every": 1000, "preview_every": 0,
                                  "progress_every": 0.0, "lpips": "off"})
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with random_init_on_purpose():
            fit(root, tmp_path / "a", config=cfg, init="random", progress=False)
            warnings.warn("another warning", MorphgsWarning)
    assert [str(w.message) for w in seen] == ["another warning"]
    with pytest.warns(MorphgsWarning, match="forward-facing"):
        fit(root, tmp_path / "b", config=cfg, init="random", progress=False)
