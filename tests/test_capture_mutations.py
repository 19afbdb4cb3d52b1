"""Every camera reader, fed mutated copies of real capture layouts, either loads valid cameras or
raises CaptureError naming the mutated file: never another exception type, never a camera that
is not one (non-finite, not a rotation, a focal or principal point out of range), never a
warning (NumPy's overflow RuntimeWarning was the only sign of a 1e300 rotation entry before).

The captures: a COLMAP model (.txt and .bin), a nerfstudio transforms.json (with
`applied_transform` and distortion, as ns-process-data writes it), an INRIA cameras.json (as
`morphgs fit` writes it) and a camera_path.json, all holding the three real cameras of the
Mip-NeRF 360 garden scene (fixtures/gsplat_test_garden.npz, see fixtures/ATTRIBUTION.md:
float32 poses, 648x420) and three orbit cameras of other sizes and models. The mutations are
seeded (`random.Random`): numbers set to 1e300 / NaN / Inf / 0 / -1 / 1e-300 / a huge integer or
flipped in sign, tokens dropped or added, lines dropped, duplicated or swapped, files cut at
random offsets, binary bytes overwritten, binary record counts changed, trailing bytes added.
"""

from __future__ import annotations

import json
import math
import random
import struct
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from capture_helpers import Shot, orbit_poses, pinhole, write_colmap
from morphgs.camera import Camera
from morphgs.curation.sources import read_inria_cameras
from morphgs.trajectory import CaptureError, from_camera_path, read_colmap_views, read_transforms_frames
from morphgs.trajectory.checks import FOCAL_RANGE, MAX_COORDINATE, MAX_SIDE, ROTATION_TOL

_GL = np.diag([1.0, -1.0, -1.0, 1.0])
MUTATIONS = 120  # per capture file; all of them take about ten seconds
OUTCOMES: Counter[tuple[str, str, str]] = Counter()  # (file kind, mutation, loaded | raised)


def _cameras(fixtures_dir: Path) -> list[Shot]:
    d = np.load(fixtures_dir / "gsplat_test_garden.npz")
    w, h = int(d["width"]), int(d["height"])
    shots = []
    for i, (v, k) in enumerate(zip(d["viewmats"], d["Ks"])):
        k = k.astype(np.float64)
        cam = Camera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], w, h, v.astype(np.float64))
        shots.append(Shot(f"garden_{i:02d}.jpg", cam, "PINHOLE"))
    for i, w2c in enumerate(orbit_poses(3)):
        size = ((64, 48), (48, 64), (33, 24))[i]
        c = pinhole(w2c, *size)
        model, params = (("SIMPLE_RADIAL", (c.fx, c.cx, c.cy, -0.05)), ("OPENCV", (c.fx, c.fy, c.cx, c.cy, -0.1, 0.02,
                                                                                    0.001, 0.0)),
                         ("SIMPLE_PINHOLE", ()))[i]
        shots.append(Shot(f"orbit_{i:02d}.png", c, model, params))
    return shots


# ---- the captures ----

def _colmap(root: Path, shots: list[Shot], binary: bool) -> Path:
    model = write_colmap(root / "sparse" / "0", shots, binary=binary)
    if not binary:  # give one image 2D points, as a real model has
        lines = (model / "images.txt").read_text().splitlines()
        lines[2] = "10.5 20.5 -1 11.25 22.0 7 300.0 200.5 12"
        (model / "images.txt").write_text("\n".join(lines) + "\n")
    return model


def _transforms(root: Path, shots: list[Shot]) -> Path:
    # ns-process-data: c2w_file = A @ c2w_colmap with A its applied_transform
    a = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    frames = []
    for s in shots:
        c = s.camera
        frames.append({"file_path": f"images/{s.name}", "transform_matrix": (a @ c.camera_to_world @ _GL).tolist(),
                       "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height})
    meta = {"camera_model": "OPENCV", "k1": -0.01, "k2": 0.002, "p1": 0.0, "p2": 0.0,
            "applied_transform": a[:3].tolist(), "frames": frames}
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps(meta, indent=2))
    return root / "transforms.json"


def _inria(root: Path, shots: list[Shot]) -> Path:
    out = []
    for i, s in enumerate(shots[:3]):  # one size: a Cameras path needs one
        c, c2w = s.camera, s.camera.camera_to_world
        out.append({"id": i, "img_name": Path(s.name).stem, "width": c.width, "height": c.height,
                    "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(), "fx": c.fx, "fy": c.fy})
    root.mkdir(parents=True, exist_ok=True)
    (root / "cameras.json").write_text(json.dumps(out))
    return root / "cameras.json"


def _camera_path(root: Path, shots: list[Shot]) -> Path:
    keys = [{"camera_to_world": (s.camera.camera_to_world @ _GL).reshape(-1).tolist(), "fov": 50.0 + 5 * i,
             "aspect": 648 / 420} for i, s in enumerate(shots)]
    meta = {"camera_type": "perspective", "render_width": 648, "render_height": 420, "camera_path": keys}
    root.mkdir(parents=True, exist_ok=True)
    (root / "camera_path.json").write_text(json.dumps(meta))
    return root / "camera_path.json"


# ---- what a loaded camera must be ----

def _valid(cams: list[Camera]) -> None:
    assert cams
    for c in cams:
        assert 0 < c.width <= MAX_SIDE and 0 < c.height <= MAX_SIDE
        side = max(c.width, c.height)
        for f in (c.fx, c.fy):
            assert FOCAL_RANGE[0] * side <= f <= FOCAL_RANGE[1] * side, c
        assert abs(c.cx - c.width / 2) <= c.width and abs(c.cy - c.height / 2) <= c.height, c
        m = c.world_to_camera
        assert np.all(np.isfinite(m))
        np.testing.assert_array_equal(m[3], [0.0, 0.0, 0.0, 1.0])
        r = m[:3, :3]
        assert np.abs(r.T @ r - np.eye(3)).max() <= ROTATION_TOL and np.linalg.det(r) > 0, r
        assert np.abs(c.center).max() <= 2 * MAX_COORDINATE


def _read_colmap(model: Path) -> list[Camera]:
    return [v.camera for v in read_colmap_views(model)]


def _read_transforms(path: Path) -> list[Camera]:
    frames = read_transforms_frames(path)
    for f in frames:
        assert all(math.isfinite(v) for v in f.distortion.values())
    return [f.camera for f in frames]


def _load_or_capture_error(kind: str, op: str, read: Callable[[], list[Camera]], mutated: Path) -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a NumPy RuntimeWarning is a failure, not a sign
            cams = read()
    except CaptureError as e:
        assert str(mutated) in str(e), (op, str(e))
        assert "\n" not in str(e)
        OUTCOMES[(kind, op, "raised")] += 1
        return
    _valid(cams)
    OUTCOMES[(kind, op, "loaded")] += 1


# ---- mutations ----

_VALUES: list[Any] = [1e300, -1e300, float("nan"), float("inf"), 0, -1.0, 1e-300, 10**400, "x", None]


def _leaves(x: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    if isinstance(x, dict):
        return [p for k, v in x.items() for p in _leaves(v, path + (k,))]
    if isinstance(x, list):
        return [p for i, v in enumerate(x) for p in _leaves(v, path + (i,))]
    return [path] if isinstance(x, (int, float)) and not isinstance(x, bool) else []


def _containers(x: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    kids: list[tuple[Any, ...]] = []
    if isinstance(x, dict):
        kids = [p for k, v in x.items() for p in _containers(v, path + (k,))]
    elif isinstance(x, list):
        kids = [p for i, v in enumerate(x) for p in _containers(v, path + (i,))]
    return ([path] if isinstance(x, (dict, list)) and x else []) + kids


def _at(doc: Any, path: tuple[Any, ...]) -> Any:
    for k in path:
        doc = doc[k]
    return doc


def _mutate_json(text: str, rng: random.Random) -> tuple[str, str]:
    doc = json.loads(text)
    op = rng.choice(["value", "value", "value", "flip", "remove", "cut"])
    if op == "cut":
        return text[: rng.randrange(len(text))], op
    if op == "remove":  # a key or a list entry gone
        c = _at(doc, rng.choice(_containers(doc)))
        if isinstance(c, dict):
            del c[rng.choice(list(c))]
        else:
            del c[rng.randrange(len(c))]
        return json.dumps(doc), op
    path = rng.choice(_leaves(doc))
    parent = _at(doc, path[:-1])
    if op == "flip":
        parent[path[-1]] = -parent[path[-1]]
    else:
        v = rng.choice(_VALUES)
        parent[path[-1]] = v
        op = f"set {v!r}"[:16]
    return json.dumps(doc), op


_TOKENS = ["1e300", "-1e300", "nan", "inf", "0", "-1", "1e-300", "99", "3.5", "x", "1" + "0" * 400]


def _mutate_text(text: str, rng: random.Random) -> tuple[str, str]:
    lines = text.splitlines()
    data = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    op = rng.choice(["token", "token", "token", "flip", "drop token", "add token", "drop line", "duplicate line",
                     "swap lines", "blank line", "cut"])
    if op == "cut":
        return text[: rng.randrange(len(text))], op
    i = rng.choice(data)
    parts = lines[i].split()
    j = rng.randrange(len(parts))
    if op == "token":
        v = rng.choice(_TOKENS)
        parts[j] = v
        op = f"set {v[:8]}"
    elif op == "flip":
        parts[j] = parts[j][1:] if parts[j].startswith("-") else "-" + parts[j]
    elif op == "drop token":
        del parts[j]
    elif op == "add token":
        parts.insert(j, "0.5")
    lines[i] = " ".join(parts)
    if op == "drop line":
        del lines[rng.randrange(len(lines))]
    elif op == "duplicate line":
        lines.insert(i, lines[i])
    elif op == "swap lines":
        k = rng.randrange(len(lines))
        lines[i], lines[k] = lines[k], lines[i]
    elif op == "blank line":
        lines.insert(rng.randrange(len(lines) + 1), "")
    return "\n".join(lines) + "\n", op


def _doubles(data: bytes, kind: str) -> list[int]:
    """Offsets of the float64 fields of a cameras.bin / images.bin (parameters; qvec, tvec)."""
    out, pos = [], 8
    for _ in range(struct.unpack_from("<Q", data)[0]):
        if kind == "cameras.bin":
            mid = struct.unpack_from("<i", data, pos + 4)[0]
            n = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8}[mid]
            out += [pos + 24 + 8 * k for k in range(n)]
            pos += 24 + 8 * n
        else:
            out += [pos + 4 + 8 * k for k in range(7)]
            end = data.index(b"\x00", pos + 64)
            npts = struct.unpack_from("<Q", data, end + 1)[0]
            pos = end + 9 + 24 * npts
    return out


def _mutate_bin(data: bytes, kind: str, rng: random.Random) -> tuple[bytes, str]:
    b = bytearray(data)
    op = rng.choice(["double", "double", "double", "bytes", "count", "cut", "trailing"])
    if op == "double":
        v = rng.choice([1e300, -1e300, math.nan, math.inf, 0.0, -1.0, 1e-300, 2.0])
        struct.pack_into("<d", b, rng.choice(_doubles(data, kind)), v)
        op = f"set {v!r}"
    elif op == "bytes":
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(len(b))] = rng.randrange(256)
    elif op == "count":
        struct.pack_into("<Q", b, 0, rng.choice([0, 1, struct.unpack_from("<Q", data)[0] + 1, 2**31, 2**63 + 5]))
    elif op == "cut":
        del b[rng.randrange(len(b)):]
    else:
        b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 40)))
    return bytes(b), op


# ---- the tests ----

@pytest.fixture(scope="module")
def shots(fixtures_dir: Path) -> list[Shot]:
    return _cameras(fixtures_dir)


def test_the_unmutated_captures_load(shots: list[Shot], tmp_path: Path) -> None:
    for binary in (False, True):
        cams = _read_colmap(_colmap(tmp_path / f"c{binary}", shots, binary))
        _valid(cams)
        assert len(cams) == 6
    t = _read_transforms(_transforms(tmp_path / "t", shots))
    _valid(t)
    # applied_transform undone: the cameras are the COLMAP ones again
    byname = {s.name: s.camera for s in shots}
    for f, c in zip(read_transforms_frames(tmp_path / "t" / "transforms.json"), t):
        np.testing.assert_allclose(c.world_to_camera, byname[Path(f.entry["file_path"]).name].world_to_camera,
                                   atol=1e-7)  # float32 poses: R^T is their inverse to 1e-7
    _valid(list(read_inria_cameras(_inria(tmp_path / "i", shots), resolution=None)))
    _valid(list(from_camera_path(_camera_path(tmp_path / "p", shots))))


@pytest.mark.parametrize("kind", ["cameras.txt", "images.txt", "cameras.bin", "images.bin"])
def test_mutated_colmap_models_load_or_raise_capture_error(kind: str, shots: list[Shot], tmp_path: Path) -> None:
    model = _colmap(tmp_path / "base", shots, binary=kind.endswith(".bin"))
    original = (model / kind).read_bytes()
    rng = random.Random(f"colmap {kind}")
    for _ in range(MUTATIONS):
        if kind.endswith(".bin"):
            data, op = _mutate_bin(original, kind, rng)
        else:
            text, op = _mutate_text(original.decode(), rng)
            data = text.encode()
        (model / kind).write_bytes(data)
        _load_or_capture_error(kind, op, lambda: _read_colmap(model), model / kind)
    kinds = {(o, r) for (k, o, r) in OUTCOMES if k == kind}
    assert {r for _, r in kinds} == {"loaded", "raised"}, kinds


@pytest.mark.parametrize("kind", ["transforms.json", "cameras.json", "camera_path.json"])
def test_mutated_json_cameras_load_or_raise_capture_error(kind: str, shots: list[Shot], tmp_path: Path) -> None:
    write: dict[str, Callable[[Path, list[Shot]], Path]] = {
        "transforms.json": _transforms, "cameras.json": _inria, "camera_path.json": _camera_path}
    read: dict[str, Callable[[Path], list[Camera]]] = {
        "transforms.json": _read_transforms,
        "cameras.json": lambda p: list(read_inria_cameras(p, resolution=None)),
        "camera_path.json": lambda p: list(from_camera_path(p)),
    }
    path = write[kind](tmp_path, shots)
    original = path.read_text()
    rng = random.Random(f"json {kind}")
    for _ in range(MUTATIONS):
        text, op = _mutate_json(original, rng)
        path.write_text(text)
        _load_or_capture_error(kind, op, lambda: read[kind](path), path)
    kinds = {(o, r) for (k, o, r) in OUTCOMES if k == kind}
    assert {r for _, r in kinds} == {"loaded", "raised"}, kinds


@pytest.mark.parametrize(("entry", "value", "needle"), [
    ((0, 1), 1e300, "beyond 1"),  # the two cases: fitted "successfully" before
    ((1, 1), -1.0, "not orthonormal"),
    ((2, 3), float("nan"), "NaN"),
])
def test_a_bad_rotation_entry_names_the_file_and_the_frame(entry: tuple[int, int], value: float, needle: str,
                                                           shots: list[Shot], tmp_path: Path) -> None:
    path = _transforms(tmp_path, shots)
    meta = json.loads(path.read_text())
    meta["frames"][4]["transform_matrix"][entry[0]][entry[1]] = value
    path.write_text(json.dumps(meta))
    with pytest.raises(CaptureError, match=needle) as info:
        read_transforms_frames(path)
    assert f"{path}: frames[4] (images/orbit_01.png)" in str(info.value)


def test_a_rotation_with_rounded_digits_is_snapped_and_a_float32_one_kept(shots: list[Shot], tmp_path: Path) -> None:
    path = _transforms(tmp_path, shots)
    meta = json.loads(path.read_text())
    exact = [np.array(f["transform_matrix"]) for f in meta["frames"]]
    meta["frames"][3]["transform_matrix"] = np.round(exact[3], 4).tolist()  # off by about 1e-4
    path.write_text(json.dumps(meta))
    frames = {f.entry["file_path"]: f.camera for f in read_transforms_frames(path)}
    r = frames["images/orbit_00.png"].world_to_camera[:3, :3]
    assert np.abs(r.T @ r - np.eye(3)).max() < 1e-12  # the nearest rotation
    np.testing.assert_allclose(r, shots[3].camera.world_to_camera[:3, :3], atol=2e-4)
    # the garden poses (float32, off by 6e-8) are used exactly as written: runs keep their bytes
    g = frames["images/garden_00.jpg"].world_to_camera
    np.testing.assert_allclose(g, shots[0].camera.world_to_camera, atol=1e-7)
    assert np.abs(g[:3, :3].T @ g[:3, :3] - np.eye(3)).max() > 1e-9


@pytest.mark.parametrize(("line", "token", "value", "needle"), [
    (1, 4, "-30", "focal lengths must be positive"),
    (1, 6, "5000", "principal point"),
    (1, 2, "0", "image size"),
])
def test_a_bad_colmap_camera_names_the_file_and_line(line: int, token: int, value: str, needle: str,
                                                     shots: list[Shot], tmp_path: Path) -> None:
    model = _colmap(tmp_path, shots, binary=False)
    lines = (model / "cameras.txt").read_text().splitlines()
    parts = lines[line].split()
    parts[token] = value
    lines[line] = " ".join(parts)
    (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match=needle) as info:
        read_colmap_views(model)
    assert f"{model / 'cameras.txt'}:2: camera 1" in str(info.value)


def test_colmap_records_that_disagree_name_file_and_line(shots: list[Shot], tmp_path: Path) -> None:
    model = _colmap(tmp_path, shots, binary=False)
    text = (model / "images.txt").read_text()
    lines = text.splitlines()
    # a pose line without its points line: the next pose is not a points line
    (model / "images.txt").write_text("\n".join(lines[:2] + lines[3:]) + "\n")
    with pytest.raises(CaptureError, match=r"images.txt:3: expected the 2D points of image 1"):
        read_colmap_views(model)
    # the same image id twice
    (model / "images.txt").write_text(text + lines[3] + "\n\n")
    with pytest.raises(CaptureError, match=r"images.txt:\d+: image 2 .*used twice \(first at .*images.txt:4"):
        read_colmap_views(model)
    # a camera that is not defined
    (model / "images.txt").write_text(text.replace(" 4 orbit_00.png", " 9 orbit_00.png"))
    with pytest.raises(CaptureError, match=r"images.txt:\d+: image \d 'orbit_00.png': refers to camera 9"):
        read_colmap_views(model)


def test_a_binary_count_that_lies_allocates_nothing(shots: list[Shot], tmp_path: Path) -> None:
    model = _colmap(tmp_path, shots, binary=True)
    data = bytearray((model / "images.bin").read_bytes())
    # the last image claims 2^60 2D points: refused before any read of that size
    struct.pack_into("<Q", data, len(data) - 8, 2**60)
    (model / "images.bin").write_bytes(bytes(data))
    with pytest.raises(CaptureError, match=r"images.bin: image record 6 of 6 .* says 1152921504606846976 2D points"):
        read_colmap_views(model)
    struct.pack_into("<Q", data, 0, 2**62)
    (model / "images.bin").write_bytes(bytes(data))
    with pytest.raises(CaptureError, match=r"images.bin: the header says 4611686018427387904 images"):
        read_colmap_views(model)


def test_the_mutations_reach_both_outcomes(capsys: pytest.CaptureFixture[str]) -> None:
    """Run after the mutation tests above (file order): every reader both refused some mutated
    captures with a CaptureError and loaded others as valid cameras, so the validation is neither
    off nor refusing everything; the tally shows with pytest -s."""
    if not OUTCOMES:
        pytest.skip("run with the mutation tests of this file (it checks their outcomes)")
    for kind in sorted({k for k, _, _ in OUTCOMES}):
        loaded = sum(n for (k, _, r), n in OUTCOMES.items() if k == kind and r == "loaded")
        raised = sum(n for (k, _, r), n in OUTCOMES.items() if k == kind and r == "raised")
        ops = sorted({o for k, o, _ in OUTCOMES if k == kind})
        each = ", ".join(f"{o} {OUTCOMES[(kind, o, 'loaded')]}/{OUTCOMES[(kind, o, 'raised')]}" for o in ops)
        print(f"\n{kind}: {loaded} loaded, {raised} raised (loaded/raised: {each})", end="")
        assert raised > 0 and loaded > 0, (kind, loaded, raised)
