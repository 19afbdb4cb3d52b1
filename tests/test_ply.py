"""PLY reading and writing against an independent reader (plyfile), across encodings and types.

Fixtures: metalsplatter_train3.ply and splatapult_test.ply from tests/fixtures (ATTRIBUTION.md).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from ply_reference import (
    FIELDS,
    assert_scene_equals,
    random_vertices,
    reference_arrays,
    vertex_dtype,
    write_ply,
)

import morphgs

FIXTURES = ["metalsplatter_train3.ply", "splatapult_test.ply"]


@pytest.mark.parametrize("name", FIXTURES)
def test_fixture_loads_exactly_what_plyfile_reads(fixtures_dir: Path, name: str) -> None:
    path = fixtures_dir / name
    scene = morphgs.load(path)
    ref = reference_arrays(path)
    assert len(scene) == len(ref["means"]) and scene.sh_degree == 3
    assert_scene_equals(scene, ref)


def test_fixture_quaternions_come_out_unit_length(fixtures_dir: Path) -> None:
    raw = PlyData.read(str(fixtures_dir / "metalsplatter_train3.ply"))["vertex"].data
    norms = np.sqrt(sum(raw[f"rot_{i}"].astype(np.float64) ** 2 for i in range(4)))
    assert np.abs(norms - 1).max() > 1e-3, "the fixture's quaternions are not unit: a real test"
    scene = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    np.testing.assert_allclose(np.linalg.norm(scene.quats.astype(np.float64), axis=1), 1, atol=1e-6)


def test_f_rest_is_transposed_to_basis_major_channel_last(tmp_path: Path) -> None:
    v = random_vertices(2, vertex_dtype(9))
    for i in range(9):
        v[f"f_rest_{i}"] = i  # R: 0 1 2, G: 3 4 5, B: 6 7 8
    scene = morphgs.load(write_ply(tmp_path / "t.ply", v))
    assert scene.sh_degree == 1
    np.testing.assert_array_equal(scene.sh_rest[0], [[0, 3, 6], [1, 4, 7], [2, 5, 8]])


@pytest.mark.parametrize("name", FIXTURES)
def test_load_save_load_is_bit_exact(fixtures_dir: Path, tmp_path: Path, name: str) -> None:
    first = morphgs.load(fixtures_dir / name)
    morphgs.save_ply(first, tmp_path / "a.ply")
    second = morphgs.load(tmp_path / "a.ply")
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(second, f).view(np.uint32), getattr(first, f).view(np.uint32))
    # and saving again gives the same bytes
    morphgs.save_ply(second, tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_writer_emits_the_inria_layout(tmp_path: Path) -> None:
    scene = morphgs.synthetic.scene(300, sh_degree=2, seed=1)
    morphgs.save_ply(scene, tmp_path / "s.ply")
    ply = PlyData.read(str(tmp_path / "s.ply"))
    assert ply.header.splitlines()[1] == "format binary_little_endian 1.0"
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(24)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert all(p.val_dtype in ("f4", "<f4", "float32") for p in v.properties)
    assert not np.any(v["nx"]) and not np.any(v["nz"])
    # channel-major f_rest in the file
    np.testing.assert_array_equal(v["f_rest_9"], scene.sh_rest[:, 1, 1])


@pytest.mark.parametrize("byte_order", [">", "<"])
def test_big_and_little_endian_files_load_identically(tmp_path: Path, byte_order: str) -> None:
    v = random_vertices(50, vertex_dtype(24), seed=3)
    base = morphgs.load(write_ply(tmp_path / "le.ply", v))
    other = morphgs.load(write_ply(tmp_path / "x.ply", v, byte_order=byte_order))
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(other, f), getattr(base, f))
    assert_scene_equals(other, reference_arrays(tmp_path / "x.ply"))


def test_ascii_file_loads_identically(tmp_path: Path) -> None:
    v = random_vertices(40, vertex_dtype(45, extras=("filter_3D",)), seed=4)
    base = morphgs.load(write_ply(tmp_path / "bin.ply", v))
    text = morphgs.load(write_ply(tmp_path / "ascii.ply", v, text=True))
    assert (tmp_path / "ascii.ply").read_bytes().splitlines()[1] == b"format ascii 1.0"
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(text, f), getattr(base, f))
    np.testing.assert_array_equal(text.extras["filter_3D"], base.extras["filter_3D"])


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_double_files_load_as_the_same_float32_values(tmp_path: Path, byte_order: str) -> None:
    v32 = random_vertices(30, vertex_dtype(45), seed=5)
    v64 = v32.astype(vertex_dtype(45, ftype="f8"))
    v64["x"] += 1e-12  # a double that is not a float32: must round to nearest
    base = morphgs.load(write_ply(tmp_path / "f.ply", v32))
    dbl = morphgs.load(write_ply(tmp_path / "d.ply", v64, byte_order=byte_order))
    np.testing.assert_array_equal(dbl.means[:, 0], v64["x"].astype(np.float32))
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(dbl, f), getattr(base, f))


def test_integer_and_mixed_property_types_are_cast(tmp_path: Path) -> None:
    dtype = [(n, "f8" if n.startswith("f_rest") else "f4") for n, _ in vertex_dtype(9, normals=False)]
    dtype += [("label", "u1"), ("segment", "i2"), ("id", "i4"), ("count", "u4"), ("tag", "i1"),
              ("level", "u2")]
    v = np.zeros(3, dtype=dtype)
    v["rot_0"] = 1
    v["label"] = [0, 7, 255]
    v["segment"] = [-32768, 0, 32767]
    v["id"] = [-(2**31), 5, 2**31 - 1]
    v["count"] = [0, 16777217, 2**32 - 1]  # 16777217 is not a float32: rounds to even
    v["tag"] = [-128, 0, 127]
    v["level"] = [0, 1, 65535]
    for order in "<>":
        scene = morphgs.load(write_ply(tmp_path / f"t{order == '<'}.ply", v, byte_order=order))
        assert list(scene.extras) == ["label", "segment", "id", "count", "tag", "level"]
        for name in scene.extras:
            np.testing.assert_array_equal(scene.extras[name], v[name].astype(np.float32), err_msg=name)
        assert_scene_equals(scene, reference_arrays(tmp_path / f"t{order == '<'}.ply"))


def test_normals_are_optional(tmp_path: Path) -> None:
    v = random_vertices(20, vertex_dtype(24, normals=False), seed=6)
    scene = morphgs.load(write_ply(tmp_path / "nn.ply", v))
    assert scene.sh_degree == 2 and not scene.extras
    assert_scene_equals(scene, reference_arrays(tmp_path / "nn.ply"))


def test_properties_are_found_by_name_in_any_order(tmp_path: Path) -> None:
    dtype = vertex_dtype(24, extras=("filter_3D",))
    shuffled = [dtype[i] for i in np.random.default_rng(7).permutation(len(dtype))]
    v = random_vertices(25, shuffled, seed=7)
    scene = morphgs.load(write_ply(tmp_path / "s.ply", v))
    assert_scene_equals(scene, reference_arrays(tmp_path / "s.ply"))


def test_degree_four_and_degree_zero_files(tmp_path: Path) -> None:
    for n_rest, degree in [(72, 4), (0, 0)]:
        v = random_vertices(10, vertex_dtype(n_rest), seed=n_rest)
        scene = morphgs.load(write_ply(tmp_path / f"d{degree}.ply", v))
        assert scene.sh_degree == degree and scene.sh_rest.shape == (10, n_rest // 3, 3)
        assert_scene_equals(scene, reference_arrays(tmp_path / f"d{degree}.ply"))


def test_elements_before_the_vertex_element_are_skipped(tmp_path: Path) -> None:
    cams = np.zeros(2, dtype=[("id", "i4"), ("pose", "O")])
    cams["pose"] = [np.arange(3, dtype=np.float32), np.arange(5, dtype=np.float32)]
    cam_el = PlyElement.describe(cams, "camera", val_types={"pose": "f4"}, len_types={"pose": "u1"})
    meta = np.zeros(4, dtype=[("a", "f8"), ("b", "u1")])
    fixed = PlyElement.describe(meta, "meta")
    v = random_vertices(12, vertex_dtype(45), seed=8)
    for text in (False, True):
        p = write_ply(tmp_path / f"e{text}.ply", v, other=[cam_el, fixed], text=text)
        assert_scene_equals(morphgs.load(p), reference_arrays(p))


def test_extra_properties_are_kept_and_written_back(tmp_path: Path) -> None:
    v = random_vertices(15, vertex_dtype(45, extras=("filter_3D", "semantic")), seed=9)
    scene = morphgs.load(write_ply(tmp_path / "x.ply", v))
    assert list(scene.extras) == ["filter_3D", "semantic"]
    np.testing.assert_array_equal(scene.extras["filter_3D"], v["filter_3D"])
    morphgs.save_ply(scene, tmp_path / "y.ply")
    back = PlyData.read(str(tmp_path / "y.ply"))["vertex"]
    assert [p.name for p in back.properties][-2:] == ["filter_3D", "semantic"]
    np.testing.assert_array_equal(back["semantic"], v["semantic"])
    again = morphgs.load(tmp_path / "y.ply")
    np.testing.assert_array_equal(again.extras["semantic"], scene.extras["semantic"])


def test_subset_keeps_extras_through_a_save(tmp_path: Path) -> None:
    v = random_vertices(10, vertex_dtype(0, extras=("filter_3D",)), seed=10)
    scene = morphgs.load(write_ply(tmp_path / "x.ply", v)).subset([9, 0, 3])
    morphgs.save_ply(scene, tmp_path / "sub.ply")
    back = morphgs.load(tmp_path / "sub.ply")
    np.testing.assert_array_equal(back.extras["filter_3D"], v["filter_3D"][[9, 0, 3]])


def test_empty_scene_round_trips(tmp_path: Path) -> None:
    empty = morphgs.synthetic.scene(0, sh_degree=3)
    morphgs.save_ply(empty, tmp_path / "e.ply")
    back = morphgs.load(tmp_path / "e.ply")
    assert len(back) == 0 and back.sh_degree == 3 and back.sh_rest.shape == (0, 15, 3)


def test_zero_quaternion_becomes_identity(tmp_path: Path) -> None:
    v = random_vertices(3, vertex_dtype(0), seed=11)
    for i in range(4):
        v[f"rot_{i}"][1] = 0
    scene = morphgs.load(write_ply(tmp_path / "z.ply", v))
    np.testing.assert_array_equal(scene.quats[1], [1, 0, 0, 0])


def test_result_does_not_depend_on_thread_count(tmp_path: Path) -> None:
    v = random_vertices(20_000, vertex_dtype(45), seed=12)  # several parallel tasks
    path = write_ply(tmp_path / "t.ply", v)
    code = ("import hashlib, sys, morphgs; s = morphgs.load(sys.argv[1]); h = hashlib.sha256()\n"
            "for f in ('means','quats','log_scales','opacity_logits','sh0','sh_rest'):\n"
            "    h.update(getattr(s, f).tobytes())\n"
            "print(morphgs.num_threads(), h.hexdigest())")
    digests = set()
    for threads in ("1", "2", "5"):
        env = {**os.environ, "RAYON_NUM_THREADS": threads}
        out = subprocess.run([sys.executable, "-c", code, str(path)], env=env, check=True,
                             capture_output=True, text=True).stdout.split()
        assert out[0] == threads
        digests.add(out[1])
    assert len(digests) == 1


def test_save_overwrites_an_existing_file(tmp_path: Path) -> None:
    target = tmp_path / "s.ply"
    target.write_bytes(b"old contents")
    scene = morphgs.synthetic.scene(100, seed=2)
    morphgs.save_ply(scene, target)
    np.testing.assert_array_equal(morphgs.load(target).means, scene.means)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_load_works_in_a_child_forked_after_a_load(tmp_path: Path) -> None:
    # torch's DataLoader forks workers after the parent used the thread pool: the child must get
    # a pool of its own instead of deadlocking on the parent's (which has no threads there).
    import time
    import warnings

    path = write_ply(tmp_path / "f.ply", random_vertices(10_000, vertex_dtype(45), seed=13))
    parent = morphgs.load(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # 3.12+: fork with threads
        pid = os.fork()
    if pid == 0:  # child
        try:
            child = morphgs.load(path)
            morphgs.save_ply(child, tmp_path / "child.ply")
            os._exit(0 if np.array_equal(child.sh_rest, parent.sh_rest) else 1)
        except BaseException:
            os._exit(2)
    deadline = time.monotonic() + 60
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            pytest.fail("the forked child hung")
        time.sleep(0.02)
    assert os.waitstatus_to_exitcode(status) == 0
    assert morphgs.load(tmp_path / "child.ply").sh_rest.shape == (10_000, 15, 3)


def test_crlf_header_with_comments_loads(tmp_path: Path) -> None:
    v = random_vertices(7, vertex_dtype(9, extras=("filter_3D",)), seed=14)
    data = write_ply(tmp_path / "lf.ply", v).read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    lines.insert(2, "comment made by a Windows tool")
    lines.insert(3, "obj_info generator 1.0")
    crlf = ("\r\n".join(lines) + "\r\nend_header\r\n").encode().replace(b"ply\r\n", b"ply \r\n", 1)
    (tmp_path / "crlf.ply").write_bytes(crlf + body)
    scene = morphgs.load(tmp_path / "crlf.ply")
    assert_scene_equals(scene, reference_arrays(tmp_path / "lf.ply"))
