"""Trajectory generators: orbit/ellipse, spiral, smooth_path, for_scene, clips."""

from __future__ import annotations

import numpy as np
import pytest

from morphgs.camera import Camera, Cameras
from morphgs.trajectory import clips, ellipse, for_scene, orbit, smooth_path, spiral
from morphgs.trajectory._rotations import matrix_to_quat, quat_to_matrix, rotation_angle


def test_orbit_circles_the_centre_at_radius_and_height_and_looks_at_it() -> None:
    c = np.array([1.0, -2.0, 0.5])
    cams = orbit(c, 3.0, 1.0, 12, resolution=(64, 48))
    assert len(cams) == 12 and (cams.width, cams.height) == (64, 48)
    centres = np.stack([cam.center for cam in cams])
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2] - c[:2], axis=1), 3.0, atol=1e-12)
    np.testing.assert_allclose(centres[:, 2], 1.5, atol=1e-12)
    for cam in cams:
        np.testing.assert_allclose(cam.project(c), [[32, 24]], atol=1e-9)
    # a full turn does not repeat its first frame: 30 degree steps
    ang = np.degrees(np.arctan2(centres[:, 1] - c[1], centres[:, 0] - c[0]))
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(ang))), np.radians(30), atol=1e-12)


def test_ellipse_has_its_two_semi_axes_and_a_partial_arc_ends_where_asked() -> None:
    cams = ellipse((0, 0, 0), (4.0, 2.0), 0.0, 5, arc_degrees=90, resolution=(32, 32))
    d = np.array([np.linalg.norm(c.center) for c in cams])
    assert d[0] == pytest.approx(4.0) and d[-1] == pytest.approx(2.0)
    assert np.all((d >= 2.0 - 1e-9) & (d <= 4.0 + 1e-9))


def test_orbit_cameras_have_world_up_pointing_up_in_the_image() -> None:
    cams = orbit((0, 0, 0), 5.0, 2.0, 8, resolution=(64, 48))
    for cam in cams:
        top, bottom = cam.project([[0, 0, 0.5], [0, 0, -0.5]])
        assert top[1] < bottom[1]


def test_spiral_keeps_the_focus_point_at_the_image_centre() -> None:
    base = Camera.look_at((0, -4, 1), (0, 0, 1), width=80, height=60)
    cams = spiral(base, 20, focus_distance=4.0, radius=(0.3, 0.2, 0.1))
    for cam in cams:
        np.testing.assert_allclose(cam.project([0, 0, 1]), [[40, 30]], atol=1e-9)
    offs = np.stack([c.center for c in cams]) - base.center
    assert np.abs(offs[:, 0]).max() == pytest.approx(0.3, rel=1e-6)


def _keyframes(positions: np.ndarray, size: tuple[int, int] = (64, 48)) -> Cameras:
    return Cameras.from_list([Camera.look_at(p, p + np.array([0.0, 1.0, 0.0]), width=size[0], height=size[1])
                              for p in positions])


def test_smooth_path_passes_through_end_keyframes_at_near_constant_speed() -> None:
    # unevenly spaced keyframes on a curve; orientation constant
    t = np.array([0.0, 0.1, 0.15, 1.5, 3.0, 3.05, 5.0])
    pos = np.stack([t, np.sin(t), np.zeros_like(t)], 1)
    path = smooth_path(_keyframes(pos), 60)
    centres = np.stack([c.center for c in path])
    np.testing.assert_allclose(centres[0], pos[0], atol=1e-9)
    np.testing.assert_allclose(centres[-1], pos[-1], atol=1e-9)
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert steps.std() / steps.mean() < 0.03
    # the path is smooth: heading changes little from step to step
    d = np.diff(centres, axis=0)
    cosang = np.sum(d[1:] * d[:-1], 1) / (np.linalg.norm(d[1:], axis=1) * np.linalg.norm(d[:-1], axis=1))
    assert np.degrees(np.arccos(np.clip(cosang, -1, 1))).max() < 15  # piecewise-linear kinks here: ~60 deg


def test_smooth_path_interpolates_rotations_smoothly_between_keyframes() -> None:
    ks = Cameras.from_list([Camera.look_at((0, 0, 0), tgt, width=32, height=32)
                            for tgt in [(0, 1, 0), (1, 1, 0), (1, 0, 0), (1, -1, 0.3)]])
    path = smooth_path(ks, 40)
    q = matrix_to_quat(path.camera_to_world[:, :3, :3])
    ang = rotation_angle(q[:-1], q[1:])
    assert ang.max() < 2.0 * ang.mean()  # near-constant angular speed for a turn on the spot
    np.testing.assert_allclose(path.camera_to_world[-1], ks.camera_to_world[-1], atol=1e-9)
    np.testing.assert_allclose(path.camera_to_world[0], ks.camera_to_world[0], atol=1e-9)
    # valid rotations
    r = path.camera_to_world[:, :3, :3]
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-9)


def test_smooth_path_interpolates_intrinsics_and_handles_one_keyframe() -> None:
    a = Camera.look_at((0, 0, 0), (0, 1, 0), width=32, height=32, fov_y_degrees=40)
    b = Camera.look_at((1, 0, 0), (1, 1, 0), width=32, height=32, fov_y_degrees=60)
    path = smooth_path(Cameras.from_list([a, b]), 5)
    fx = path.K[:, 0, 0]
    assert fx[0] == pytest.approx(a.fx) and fx[-1] == pytest.approx(b.fx)
    assert np.all(np.diff(fx) < 0)
    still = smooth_path(Cameras.from_list([a]), 3)
    np.testing.assert_array_equal(still.world_to_camera, np.stack([a.world_to_camera] * 3))


def test_for_scene_ignores_floaters_when_framing() -> None:
    rng = np.random.default_rng(0)
    core = rng.uniform(-1, 1, (5000, 3))
    floaters = rng.uniform(-1, 1, (40, 3)) * 500
    clean = for_scene(core, 8, resolution=(64, 48))
    dirty = for_scene(np.concatenate([core, floaters]), 8, resolution=(64, 48))
    d_clean = np.linalg.norm(clean[0].center)
    d_dirty = np.linalg.norm(dirty[0].center)
    assert d_dirty == pytest.approx(d_clean, rel=0.05)
    for cam in dirty:  # the content stays in view
        uv = cam.project(core)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 64) & (uv[:, 1] >= 0) & (uv[:, 1] < 48)
        assert inside.mean() > 0.97


def test_clips_split_with_stride_and_drop_short_tail() -> None:
    path = orbit((0, 0, 0), 2.0, 1.0, 100, resolution=(16, 16))
    c16 = clips(path, 16)
    assert len(c16) == 6 and all(len(c) == 16 for c in c16)
    np.testing.assert_array_equal(c16[1].world_to_camera, path.world_to_camera[16:32])
    c49 = clips(path, 49, stride=25)
    assert [len(c) for c in c49] == [49, 49, 49]
    np.testing.assert_array_equal(c49[1].world_to_camera[0], path.world_to_camera[25])
    assert clips(path[:10], 16) == []
    with pytest.raises(ValueError, match="stride"):
        clips(path, 16, stride=0)


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = quat_to_matrix(q)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)


def test_cameras_dict_round_trip_and_from_c2w_opengl() -> None:
    cams = orbit((0, 0, 0), 2.0, 1.0, 4, resolution=(32, 24))
    back = Cameras.from_dict(cams.to_dict())
    np.testing.assert_array_equal(back.world_to_camera, cams.world_to_camera)
    np.testing.assert_array_equal(back.K, cams.K)
    gl = cams.camera_to_world @ np.diag([1.0, -1, -1, 1])
    again = Cameras.from_c2w(gl, K=cams.K, width=32, height=24, convention="opengl")
    np.testing.assert_allclose(again.world_to_camera, cams.world_to_camera, atol=1e-12)
