"""Trajectory readers on hand-written files with known poses: a known 3D point must land on the
pixel computed by hand (pinhole, OpenCV axes, SPEC §3)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs.trajectory import from_camera_path, from_colmap, from_transforms_json

# An OpenGL camera-to-world: camera at (0,-5,0) looking at the origin, z up.
# OpenCV axes: right (1,0,0), down (0,0,-1), forward (0,1,0); OpenGL: right, up (0,0,1), back (0,-1,0).
C2W_GL = [[1, 0, 0, 0], [0, 0, -1, -5], [0, 1, 0, 0], [0, 0, 0, 1]]
# The world point (1, 0, 0.5) is at camera coordinates (1, -0.5, 5).
POINT = np.array([1.0, 0.0, 0.5])
# ns-process-data's applied_transform: (x, y, z)_colmap -> (x, z, -y)
APPLIED = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]


def _write(path: Path, obj: object) -> Path:
    path.write_text(json.dumps(obj))
    return path


def test_transforms_json_shared_intrinsics_put_known_point_on_expected_pixel(tmp_path: Path) -> None:
    p = _write(tmp_path / "transforms.json", {
        "fl_x": 100, "fl_y": 120, "cx": 40, "cy": 30, "w": 80, "h": 60, "k1": 0.1,
        "frames": [{"file_path": "images/0.png", "transform_matrix": C2W_GL}],
    })
    cams = from_transforms_json(p)  # the file's own size unless resolution= is given
    assert (cams.width, cams.height) == (80, 60)
    np.testing.assert_allclose(cams[0].project(POINT), [[40 + 100 / 5, 30 - 120 * 0.5 / 5]], atol=1e-9)
    np.testing.assert_allclose(cams[0].project([0, 0, 0]), [[40, 30]], atol=1e-9)
    np.testing.assert_allclose(cams[0].center, [0, -5, 0], atol=1e-12)


def test_transforms_json_resize_scales_focal_and_principal_point(tmp_path: Path) -> None:
    p = _write(tmp_path / "transforms.json", {
        "fl_x": 100, "fl_y": 120, "cx": 40, "cy": 30, "w": 80, "h": 60,
        "frames": [{"file_path": "a.png", "transform_matrix": C2W_GL}],
    })
    cams = from_transforms_json(p, resolution=(160, 120))  # the same aspect: both axes x2
    c = cams[0]
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (200, 240, 80, 60, 160, 120)
    # 4:3 at 16:9: scaled x2 to cover, 15 rows cropped off the top and the bottom, and said
    with pytest.warns(morphgs.MorphgsWarning, match=r"centre-cropped to it, keeping 75 % of the view"):
        cams = from_transforms_json(p, resolution=(160, 90))
    c = cams[0]
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (200, 240, 80, 45, 160, 90)
    np.testing.assert_allclose(c.project(POINT), [[80 + 200 / 5, 45 - 240 * 0.5 / 5]], atol=1e-9)


def test_transforms_json_per_frame_intrinsics_override_shared_and_frames_sorted(tmp_path: Path) -> None:
    shifted = np.array(C2W_GL, dtype=float)
    shifted[0, 3] = 1.0  # camera moved 1 to the right: the point is now straight ahead in x
    p = _write(tmp_path / "transforms.json", {
        "fl_x": 100, "w": 80, "h": 60,
        "frames": [
            {"file_path": "img_1.png", "transform_matrix": shifted.tolist(), "fl_x": 50, "fl_y": 60,
             "cx": 41, "cy": 29},
            {"file_path": "img_0.png", "transform_matrix": C2W_GL},
        ],
    })
    cams = from_transforms_json(p, resolution=None)
    # sorted by file_path: img_0 first, with the shared fl_x (fy = fx, centred principal point)
    np.testing.assert_allclose(cams[0].project(POINT), [[40 + 100 / 5, 30 - 100 * 0.5 / 5]], atol=1e-9)
    np.testing.assert_allclose(cams[1].project(POINT), [[41, 29 - 60 * 0.5 / 5]], atol=1e-9)


def test_transforms_json_blender_camera_angle_x(tmp_path: Path) -> None:
    p = _write(tmp_path / "transforms.json", {
        "camera_angle_x": 2 * np.arctan(0.5), "w": 80, "h": 60,  # fx = 0.5*80/0.5 = 80
        "frames": [{"file_path": "a", "transform_matrix": C2W_GL}],
    })
    c = from_transforms_json(p, resolution=None)[0]
    assert c.fx == pytest.approx(80) and c.fy == pytest.approx(80)


def test_transforms_json_applied_transform_is_undone_for_colmap_frame(tmp_path: Path) -> None:
    a4 = np.vstack([np.array(APPLIED, dtype=float), [0, 0, 0, 1]])
    # the camera and the point are given in the COLMAP frame; the file holds A @ c2w
    p = _write(tmp_path / "transforms.json", {
        "fl_x": 100, "fl_y": 120, "cx": 40, "cy": 30, "w": 80, "h": 60,
        "applied_transform": APPLIED,
        "frames": [{"file_path": "a", "transform_matrix": (a4 @ np.array(C2W_GL, dtype=float)).tolist()}],
    })
    expected = [[60, 18]]
    colmap = from_transforms_json(p, resolution=None)[0]
    np.testing.assert_allclose(colmap.project(POINT), expected, atol=1e-9)
    file_frame = from_transforms_json(p, resolution=None, frame="file")[0]
    np.testing.assert_allclose(file_frame.project(a4[:3, :3] @ POINT), expected, atol=1e-9)


def test_transforms_json_dataparser_transforms_map_into_splatfacto_frame(tmp_path: Path) -> None:
    p = _write(tmp_path / "transforms.json", {
        "fl_x": 100, "fl_y": 120, "cx": 40, "cy": 30, "w": 80, "h": 60,
        "frames": [{"file_path": "a", "transform_matrix": C2W_GL}],
    })
    t = np.array([[0, -1, 0, 0.3], [1, 0, 0, -0.2], [0, 0, 1, 1.0]])  # 90 deg about z, then a shift
    dp = _write(tmp_path / "dataparser_transforms.json", {"transform": t.tolist(), "scale": 0.25})
    cam = from_transforms_json(p, resolution=None, dataparser_transforms=dp)[0]
    model_point = 0.25 * (t[:, :3] @ POINT + t[:, 3])
    np.testing.assert_allclose(cam.project(model_point), [[60, 18]], atol=1e-9)


@pytest.mark.parametrize(("payload", "field"), [
    ({"w": 80, "h": 60, "fl_x": 1}, "frames"),
    ({"w": 80, "h": 60, "frames": [{"file_path": "a"}]}, "transform_matrix"),
    ({"frames": [{"file_path": "a", "transform_matrix": C2W_GL, "fl_x": 5}]}, "'w' and 'h'"),
    ({"w": 80, "h": 60, "frames": [{"file_path": "a", "transform_matrix": C2W_GL}]}, "focal length"),
    ({"w": 80, "h": 60, "fl_x": "big", "frames": [{"transform_matrix": C2W_GL}]}, "fl_x"),
    ({"w": 80, "h": 60, "fl_x": 9, "frames": [{"transform_matrix": [[1, 2], [3, 4]]}]}, "transform_matrix"),
])
def test_transforms_json_malformed_file_names_the_field(tmp_path: Path, payload: dict, field: str) -> None:
    p = _write(tmp_path / "transforms.json", payload)
    with pytest.raises(morphgs.MorphgsError, match=field):
        from_transforms_json(p)


def test_transforms_json_missing_file_is_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        from_transforms_json(tmp_path / "nope.json")


def test_camera_path_json_fov_and_row_major_opengl_pose(tmp_path: Path) -> None:
    flat = np.array(C2W_GL, dtype=float).reshape(-1).tolist()
    p = _write(tmp_path / "camera_path.json", {
        "camera_type": "perspective", "render_width": 80, "render_height": 60, "fps": 24,
        "camera_path": [{"camera_to_world": flat, "fov": 90, "aspect": 80 / 60}] * 2,
    })
    cams = from_camera_path(p)
    assert len(cams) == 2 and (cams.width, cams.height) == (80, 60)
    # f = 60 / (2 tan 45deg) = 30, principal point at the centre
    np.testing.assert_allclose(cams[1].project(POINT), [[40 + 30 / 5, 30 - 30 * 0.5 / 5]], atol=1e-9)


def test_camera_path_rejects_equirectangular(tmp_path: Path) -> None:
    p = _write(tmp_path / "camera_path.json", {"camera_type": "equirectangular", "render_height": 4,
                                               "render_width": 8, "camera_path": []})
    with pytest.raises(morphgs.MorphgsError, match="camera_type"):
        from_camera_path(p)


# ---- COLMAP ----
# image "b.png": identity rotation, t = (0,0,5): camera at (0,0,-5) looking along +z.
# image "a.png": 90 deg about y (q = (cos45, 0, sin45, 0)), t = (2,0,5).
# The point (1,-0.5,0) seen by b and (0,-0.5,-1) seen by a are both at camera coords (1,-0.5,5).
_S = float(np.sqrt(0.5))
_IMAGES = [(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 5.0), 1, "b.png"),
           (2, (_S, 0.0, _S, 0.0), (2.0, 0.0, 5.0), 2, "a.png")]
_CAMERAS = [(1, "PINHOLE", 1, 80, 60, (100.0, 120.0, 40.0, 30.0)),
            (2, "SIMPLE_RADIAL", 2, 80, 60, (100.0, 40.0, 30.0, 0.01))]


def _write_colmap_txt(d: Path) -> None:
    d.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:"]
    lines += [f"{cid} {name} {w} {h} " + " ".join(map(repr, params)) for cid, name, _, w, h, params in _CAMERAS]
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    for iid, q, t, cid, name in _IMAGES:
        lines.append(f"{iid} {' '.join(map(repr, q))} {' '.join(map(repr, t))} {cid} {name}")
        lines.append("10.0 20.0 -1 11.5 21.5 3" if iid == 1 else "")
    (d / "images.txt").write_text("\n".join(lines) + "\n")


def _write_colmap_bin(d: Path) -> None:
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(_CAMERAS)))
        for cid, _, mid, w, h, params in _CAMERAS:
            f.write(struct.pack("<iiQQ", cid, mid, w, h))
            f.write(struct.pack(f"<{len(params)}d", *params))
    with open(d / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(_IMAGES)))
        for iid, q, t, cid, name in _IMAGES:
            f.write(struct.pack("<i7di", iid, *q, *t, cid))
            f.write(name.encode() + b"\x00")
            pts = [(10.0, 20.0, -1), (11.5, 21.5, 3)] if iid == 1 else []
            f.write(struct.pack("<Q", len(pts)))
            for x, y, pid in pts:
                f.write(struct.pack("<ddq", x, y, pid))


@pytest.mark.parametrize("form", ["txt", "bin"])
def test_colmap_known_points_land_on_expected_pixels(tmp_path: Path, form: str) -> None:
    model = tmp_path / "scene" / "sparse" / "0"
    (_write_colmap_txt if form == "txt" else _write_colmap_bin)(model)
    cams = from_colmap(tmp_path / "scene", resolution=None)
    assert len(cams) == 2
    # sorted by name: a.png (SIMPLE_RADIAL, f=100) first, then b.png (PINHOLE)
    np.testing.assert_allclose(cams[0].project([0.0, -0.5, -1.0]), [[40 + 100 / 5, 30 - 100 * 0.5 / 5]], atol=1e-9)
    np.testing.assert_allclose(cams[1].project([1.0, -0.5, 0.0]), [[60, 18]], atol=1e-9)
    np.testing.assert_allclose(cams[1].center, [0, 0, -5], atol=1e-12)


def test_colmap_text_and_binary_give_the_same_cameras(tmp_path: Path) -> None:
    _write_colmap_txt(tmp_path / "t")
    _write_colmap_bin(tmp_path / "b")
    a, b = from_colmap(tmp_path / "t"), from_colmap(tmp_path / "b")
    assert (a.width, a.height) == (b.width, b.height) == (80, 60)  # the recorded size by default
    np.testing.assert_array_equal(a.world_to_camera, b.world_to_camera)
    np.testing.assert_array_equal(a.K, b.K)


def test_colmap_truncated_binary_is_a_clear_error(tmp_path: Path) -> None:
    _write_colmap_bin(tmp_path)
    data = (tmp_path / "images.bin").read_bytes()
    (tmp_path / "images.bin").write_bytes(data[:40])
    with pytest.raises(morphgs.MorphgsError, match="images.bin"):
        from_colmap(tmp_path)


def test_colmap_fisheye_warns_that_distortion_is_ignored(tmp_path: Path) -> None:
    _write_colmap_txt(tmp_path)
    (tmp_path / "cameras.txt").write_text(
        "1 OPENCV_FISHEYE 80 60 100 120 40 30 0 0 0 0\n2 PINHOLE 80 60 100 100 40 30\n")
    with pytest.warns(morphgs.MorphgsWarning, match="fisheye"):
        cams = from_colmap(tmp_path, resolution=None)
    assert cams[1].fx == 100 and cams[1].fy == 120


def test_colmap_missing_model_is_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="COLMAP"):
        from_colmap(tmp_path)
