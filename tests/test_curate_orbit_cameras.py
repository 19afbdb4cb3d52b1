"""`curate --trajectory orbit` on a scene with recorded cameras circles what the cameras look at.

A real capture's Gaussians spread far beyond its subject (background, sky, floaters): the box of
their centres frames mostly emptiness. The orbit follows the cameras instead: their focus point
(the least-squares point nearest to every optical axis), their mean up, their median distance,
elevation and field of view (`trajectory.around_cameras`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

import morphgs
from morphgs import trajectory
from morphgs.camera import Cameras
from morphgs.cli import main
from morphgs.curation import load_manifest

_GL = np.diag([1.0, -1.0, -1.0, 1.0])
SUBJECT = np.array([40.0, -3.0, 25.0])  # far from the origin and from the background's centre


def _capture(root: Path) -> Cameras:
    """A scene folder: a small red subject at SUBJECT inside 6000 blue background Gaussians spread
    over a 400-unit box (y down, as scene files are), and 12 recorded cameras around the subject."""
    rng = np.random.default_rng(3)
    n_s, n_b = 800, 6000
    subject = SUBJECT + rng.normal(0.0, 0.25, (n_s, 3))
    background = rng.uniform(-200.0, 200.0, (n_b, 3)) + np.array([-80.0, 0.0, -60.0])
    means = np.concatenate([subject, background]).astype(np.float32)
    n = n_s + n_b
    quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1))
    log_scales = np.concatenate([np.full((n_s, 3), np.log(0.08)), np.full((n_b, 3), np.log(2.0))]).astype(np.float32)
    color = np.concatenate([np.tile([1.0, 0.05, 0.05], (n_s, 1)), np.tile([0.05, 0.05, 1.0], (n_b, 1))])
    sh0 = ((color - 0.5) / 0.28209479177387814).astype(np.float32)
    scene = morphgs.GaussianScene.from_arrays(means=means, quats=quats, log_scales=log_scales,
                                              opacity_logits=np.full(n, 3.0, np.float32), sh0=sh0)
    root.mkdir(parents=True)
    morphgs.save(scene, root / "scene.ply")
    cams = trajectory.orbit(SUBJECT, 3.0, 1.0, 12, up=(0.0, -1.0, 0.0), fov_y_degrees=40.0, resolution=(64, 48))
    c0 = cams[0]
    frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": (c.camera_to_world @ _GL).tolist()}
              for i, c in enumerate(cams)]
    meta = {"fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy, "w": 64, "h": 48, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta), encoding="utf-8")
    return cams


def test_camera_focus_finds_the_point_the_cameras_look_at_and_their_up(tmp_path: Path) -> None:
    cams = _capture(tmp_path / "cap")
    focus, up, converged = trajectory.camera_focus(cams)
    assert converged
    np.testing.assert_allclose(focus, SUBJECT, atol=1e-6)
    np.testing.assert_allclose(up, [0.0, -1.0, 0.0], atol=1e-9)
    # forward-facing cameras (parallel axes) have no common focus: said, and a finite point ahead
    c2w = np.stack([np.eye(4) for _ in range(4)])
    c2w[:, 0, 3] = [0.0, 0.1, 0.2, 0.3]
    ff = Cameras.from_c2w(c2w, K=np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), width=64, height=48)
    f2, _, conv2 = trajectory.camera_focus(ff)
    assert not conv2 and np.all(np.isfinite(f2)) and f2[2] > 0


def test_curate_orbit_of_a_scene_with_cameras_frames_the_subject_not_the_background(tmp_path: Path) -> None:
    _capture(tmp_path / "cap")
    out = tmp_path / "out"
    rc = main(["curate", str(tmp_path / "cap"), "--out", str(out), "--trajectory", "orbit", "-k", "2",
               "--frames", "4", "--size", "64x48", "--no-progress", "--test-fraction", "0"])
    assert rc == 0
    recs = load_manifest(out)
    assert len(recs) == 2
    for rec in recs.values():
        assert rec["up_rule"] == "cameras"
        np.testing.assert_allclose(rec["up"], [0.0, -1.0, 0.0], atol=1e-9)
        cams = Cameras.from_dict(json.loads((out / rec["paths"]["cameras"]).read_text()))
        centres = np.asarray(cams.camera_to_world)[:, :3, 3]
        # at the recorded cameras' distance from the subject (sqrt(3^2 + 1^2))
        np.testing.assert_allclose(np.linalg.norm(centres - SUBJECT, axis=1), np.sqrt(10.0), rtol=1e-6)
        for i, cam in enumerate(cams):
            p = cam.world_to_camera @ np.append(SUBJECT, 1.0)
            assert p[2] > 0  # in front of the camera, at the image centre
            np.testing.assert_allclose([cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy], [32, 24],
                                       atol=1e-6)
            img = np.asarray(Image.open(out / rec["paths"]["clean"] / f"{i:05d}.png").convert("RGB"), np.float64)
            centre = img[16:32, 22:42]
            assert (centre[..., 0] > 2 * centre[..., 2]).mean() > 0.5  # the red subject fills the centre
    # the same pairs' orbit around the box of all centres (the old framing) would miss it
    old = trajectory.for_scene(morphgs.load(tmp_path / "cap" / "scene.ply"), 4, resolution=(64, 48), up="file")
    p = old[0].world_to_camera @ np.append(SUBJECT, 1.0)
    assert p[2] > 0 and old[0].fy * 0.75 / p[2] < 1.0  # the subject (radius 0.75, 3 sigma) under a pixel


def test_a_pair_size_of_another_aspect_than_the_capture_warns_with_a_size_to_use(tmp_path: Path) -> None:
    import pytest

    _capture(tmp_path / "cap")  # 64x48 cameras (aspect 1.33)
    out = tmp_path / "out"
    with pytest.warns(morphgs.MorphgsWarning, match=r"centre-cropped to it, keeping 67 % of the view; pass a size "
                                                    r"of the capture's aspect to keep it whole, e\.g\. --size 64x48"):
        rc = main(["curate", str(tmp_path / "cap"), "--out", str(out), "-k", "1", "--frames", "2",
                   "--size", "96x48", "--no-progress", "--test-fraction", "0"])
    assert rc == 0
    # within 5 % (DL3DV's 16:9 at the paper's 832x480 is 2.6 %) it stays quiet
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        trajectory.from_transforms_json(tmp_path / "cap" / "transforms.json", resolution=(66, 48))
