"""Every malformed-file case raises SceneFormatError naming the file, the element or property and
the problem; nothing crashes, hangs or allocates what the header merely claims."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ply_reference import header_bytes, random_vertices, vertex_dtype, write_ply

import morphgs

REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _format_error(path: Path) -> morphgs.SceneFormatError:
    with pytest.raises(morphgs.SceneFormatError) as info:
        morphgs.load(path)
    err = info.value
    assert isinstance(err, morphgs.MorphgsError) and isinstance(err, ValueError)
    assert str(path) in str(err), str(err)
    assert err.path == str(path)
    return err


def _good_ply(tmp_path: Path, n: int = 10, name: str = "good.ply") -> Path:
    return write_ply(tmp_path / name, random_vertices(n, vertex_dtype(45)))


def test_not_a_ply(tmp_path: Path) -> None:
    p = tmp_path / "notes.ply"
    p.write_bytes(b"hello, this is a text file\n" * 3)
    err = _format_error(p)
    assert "not a PLY" in str(err) or "unrecognised scene format" in str(err)


def test_empty_file(tmp_path: Path) -> None:
    p = tmp_path / "empty.ply"
    p.write_bytes(b"")
    assert "empty" in str(_format_error(p))


def test_unsupported_format_line(tmp_path: Path) -> None:
    p = tmp_path / "fmt.ply"
    p.write_bytes(header_bytes(REQUIRED, 0, fmt="binary_middle_endian 1.0"))
    err = _format_error(p)
    assert "unsupported format line" in str(err) and "binary_middle_endian" in str(err)


def test_missing_format_line(tmp_path: Path) -> None:
    p = tmp_path / "nofmt.ply"
    p.write_bytes(b"ply\nelement vertex 0\nproperty float x\nend_header\n")
    assert "no 'format' line" in str(_format_error(p))


def test_header_without_end_header(tmp_path: Path) -> None:
    p = tmp_path / "cut.ply"
    p.write_bytes(header_bytes(REQUIRED, 1)[:-20])
    assert "end_header" in str(_format_error(p))


def test_unknown_property_type(tmp_path: Path) -> None:
    p = tmp_path / "type.ply"
    p.write_bytes(header_bytes(REQUIRED[:-1] + ["property quaternion rot_3"], 0))
    assert "unknown property type 'quaternion'" in str(_format_error(p))


def test_no_vertex_element(tmp_path: Path) -> None:
    p = tmp_path / "face.ply"
    p.write_bytes(header_bytes(["property int a"], 0, element="face"))
    err = _format_error(p)
    assert "no 'vertex' element" in str(err) and "face" in str(err)


def test_missing_required_properties_are_all_listed(tmp_path: Path) -> None:
    dtype = [d for d in vertex_dtype(45) if d[0] not in ("opacity", "rot_3", "y")]
    p = write_ply(tmp_path / "missing.ply", random_vertices(4, dtype))
    err = _format_error(p)
    assert err.element == "vertex" and "element 'vertex'" in str(err)
    assert "missing required properties: y, opacity, rot_3" in str(err)


@pytest.mark.parametrize("n_rest", [10, 27, 3])
def test_f_rest_count_that_is_no_sh_degree(tmp_path: Path, n_rest: int) -> None:
    p = write_ply(tmp_path / "rest.ply", random_vertices(4, vertex_dtype(n_rest)))
    err = _format_error(p)
    assert err.property == "f_rest_*"
    assert f"{n_rest} f_rest properties is no SH degree" in str(err)


def test_f_rest_with_a_gap_names_the_missing_one(tmp_path: Path) -> None:
    dtype = [("f_rest_99", "f4") if d[0] == "f_rest_4" else d for d in vertex_dtype(9)]
    err = _format_error(write_ply(tmp_path / "gap.ply", random_vertices(4, dtype)))
    assert err.property == "f_rest_4" and "f_rest_4" in str(err)


def test_list_property_in_the_vertex_element(tmp_path: Path) -> None:
    p = tmp_path / "list.ply"
    p.write_bytes(header_bytes(REQUIRED + ["property list uchar int vertex_indices"], 1)
                  + b"\0" * 64)
    err = _format_error(p)
    assert err.element == "vertex" and err.property == "vertex_indices"
    assert "list propert" in str(err)


def test_duplicate_property(tmp_path: Path) -> None:
    p = tmp_path / "dup.ply"
    p.write_bytes(header_bytes(REQUIRED + ["opacity"], 1) + b"\0" * 60)
    err = _format_error(p)
    assert err.property == "opacity" and "declared twice" in str(err)


def test_truncated_data_says_how_many_vertices_were_read(tmp_path: Path) -> None:
    good = _good_ply(tmp_path, n=5)
    data = good.read_bytes()
    stride = 62 * 4
    p = tmp_path / "trunc.ply"
    p.write_bytes(data[: len(data) - 2 * stride + 10])  # 3 whole vertices and a piece of the 4th
    err = _format_error(p)
    assert err.element == "vertex"
    assert "truncated" in str(err) and "3 of 5 vertices" in str(err)


def test_truncated_ascii_data_says_how_many_rows_were_read(tmp_path: Path) -> None:
    v = random_vertices(6, vertex_dtype(0))
    data = write_ply(tmp_path / "a.ply", v, text=True).read_bytes()
    p = tmp_path / "trunc_ascii.ply"
    p.write_bytes(data[: data.rindex(b"\n", 0, len(data) - 1) + 1])  # drop the last row
    err = _format_error(p)
    assert "truncated: read 5 of 6 rows" in str(err)


def test_ascii_value_that_is_not_a_number(tmp_path: Path) -> None:
    data = write_ply(tmp_path / "a.ply", random_vertices(2, vertex_dtype(0)), text=True).read_bytes()
    head, body = data.split(b"end_header\n")
    rows = body.split(b"\n")
    fields = rows[1].split(b" ")
    fields[6] = b"oops"  # columns: x y z nx ny nz f_dc_0 ...
    rows[1] = b" ".join(fields)
    p = tmp_path / "nan_text.ply"
    p.write_bytes(head + b"end_header\n" + b"\n".join(rows))
    err = _format_error(p)
    assert err.property == "f_dc_0" and "vertex 1: 'oops' is not a number" in str(err)


def test_vertex_count_the_file_cannot_hold_fails_before_allocating(tmp_path: Path) -> None:
    p = tmp_path / "lie.ply"
    p.write_bytes(header_bytes(REQUIRED, 10**15) + b"\0" * 56 * 4)
    err = _format_error(p)
    assert "cannot hold" in str(err) and "1000000000000000" in str(err)


def test_moderate_lying_count_allocates_nothing(tmp_path: Path) -> None:
    # 60M claimed vertices would be ~3.4 GB of arrays; the file holds 4. Measure the peak resident
    # size of a fresh process around the call.
    p = tmp_path / "lie.ply"
    p.write_bytes(header_bytes(REQUIRED, 60_000_000) + b"\0" * 56 * 4)
    code = r"""
import json, sys, morphgs
def kib(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1])
open("/proc/self/clear_refs", "w").write("5")
before = kib("VmRSS")
try:
    morphgs.load(sys.argv[1])
except morphgs.SceneFormatError as e:
    print(json.dumps({"grew_kib": kib("VmHWM") - before, "msg": str(e)}))
"""
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux /proc/self/clear_refs")
    out = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True,
                         check=True)
    res = json.loads(out.stdout)
    assert "cannot hold" in res["msg"]
    assert res["grew_kib"] < 16 * 1024, res


def test_nan_or_inf_raises_by_default_naming_vertex_and_property(tmp_path: Path) -> None:
    v = random_vertices(10, vertex_dtype(45))
    v["opacity"][3] = np.nan
    v["f_rest_20"][7] = np.inf
    p = write_ply(tmp_path / "nan.ply", v)
    err = _format_error(p)
    assert err.element == "vertex" and err.property == "opacity"
    assert "vertex 3 holds NaN" in str(err) and "2 of 10 Gaussians" in str(err)
    assert 'on_invalid="drop"' in str(err)


def test_nan_or_inf_dropped_on_request_with_a_warning(tmp_path: Path) -> None:
    v = random_vertices(10, vertex_dtype(45, extras=("filter_3D",)))
    v["x"][0] = -np.inf
    v["rot_2"][5] = np.nan
    v["f_rest_44"][9] = np.inf
    p = write_ply(tmp_path / "nan.ply", v)
    with pytest.warns(morphgs.MorphgsWarning, match="dropped 3 of 10 Gaussians"):
        scene = morphgs.load(p, on_invalid="drop")
    keep = [1, 2, 3, 4, 6, 7, 8]
    assert len(scene) == 7
    np.testing.assert_array_equal(scene.means[:, 1], v["y"][keep])
    np.testing.assert_array_equal(scene.extras["filter_3D"], v["filter_3D"][keep])
    assert np.isfinite(scene.sh_rest).all()


def test_nan_in_an_extra_property_is_kept(tmp_path: Path) -> None:
    v = random_vertices(4, vertex_dtype(0, extras=("filter_3D",)))
    v["filter_3D"][2] = np.nan
    scene = morphgs.load(write_ply(tmp_path / "x.ply", v))
    assert len(scene) == 4 and np.isnan(scene.extras["filter_3D"][2])


def test_on_invalid_must_be_error_or_drop(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="on_invalid"):
        morphgs.load(_good_ply(tmp_path), on_invalid="ignore")


def test_missing_file_raises_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError) as info:
        morphgs.load(tmp_path / "nope.ply")
    assert info.value.filename == str(tmp_path / "nope.ply")


def test_directory_raises_is_a_directory(tmp_path: Path) -> None:
    with pytest.raises(IsADirectoryError):
        morphgs.load(tmp_path)


def test_garbage_after_a_valid_header_never_crashes(tmp_path: Path) -> None:
    # random bodies of random lengths behind real headers (binary and ASCII): either a scene or a
    # SceneFormatError, never anything else
    rng = np.random.default_rng(0)
    for fmt in ("binary_little_endian 1.0", "binary_big_endian 1.0", "ascii 1.0"):
        for _ in range(20):
            count = int(rng.integers(0, 50))
            body = rng.integers(0, 256, int(rng.integers(0, 4000)), dtype=np.uint8).tobytes()
            if fmt.startswith("ascii"):
                body = body.replace(b"\0", b" ")
            p = tmp_path / "g.ply"
            p.write_bytes(header_bytes(REQUIRED, count, fmt=fmt) + body)
            try:
                morphgs.load(p)
            except morphgs.SceneFormatError as e:
                assert str(p) in str(e)


def test_save_into_a_missing_directory_leaves_nothing(tmp_path: Path) -> None:
    scene = morphgs.synthetic.scene(10)
    with pytest.raises(FileNotFoundError):
        morphgs.save_ply(scene, tmp_path / "no" / "such" / "dir" / "s.ply")
    assert list(tmp_path.iterdir()) == []


def test_save_onto_a_directory_keeps_it_and_leaves_no_temporary(tmp_path: Path) -> None:
    (tmp_path / "target").mkdir()
    (tmp_path / "target" / "inside.txt").write_text("keep me")
    with pytest.raises(OSError):
        morphgs.save_ply(morphgs.synthetic.scene(10), tmp_path / "target")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["target"]
    assert (tmp_path / "target" / "inside.txt").read_text() == "keep me"


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_FSIZE behaviour is Linux-specific")
def test_failed_write_does_not_clobber_the_destination(tmp_path: Path) -> None:
    # A write that fails half-way (file-size limit hit after 64 KiB) must leave the old file intact
    # and remove the temporary.
    target = tmp_path / "scene.ply"
    target.write_bytes(b"the previous scene")
    code = r"""
import resource, signal, sys, morphgs
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (65536, resource.RLIM_INFINITY))
try:
    morphgs.save_ply(morphgs.synthetic.scene(20000), sys.argv[1])
except OSError as e:
    print("failed:", e)
"""
    out = subprocess.run([sys.executable, "-c", code, str(target)], capture_output=True, text=True,
                         check=True, env=os.environ.copy())
    assert out.stdout.startswith("failed:"), out
    assert target.read_bytes() == b"the previous scene"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


def test_read_only_directory_refuses_the_write(tmp_path: Path) -> None:
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        pytest.skip("root ignores directory permissions")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(PermissionError):
            morphgs.save_ply(morphgs.synthetic.scene(10), ro / "s.ply")
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def test_bad_extra_names_are_refused_before_writing(tmp_path: Path) -> None:
    a = morphgs.synthetic.scene(3)
    arrays = dict(means=a.means, quats=a.quats, log_scales=a.log_scales,
                  opacity_logits=a.opacity_logits, sh0=a.sh0)
    for bad in ("two words", "x", "f_rest_0", ""):
        with pytest.raises(ValueError):
            morphgs.GaussianScene.from_arrays(**arrays, extras={bad: np.zeros(3)})
