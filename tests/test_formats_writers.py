""".spz v4 and SuperSplat compressed-PLY writers, `morphgs.save` / `morphgs convert` picking the
writer by name, and the .spz extension records and v1 layout of nianticlabs/spz."""

from __future__ import annotations

import gzip
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import morphgs

MAGIC = 0x5053474E


def test_spz_v4_writes_the_v3_quantisation_in_zstd_streams(fixtures_dir: Path,
                                                           tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / "splatapult_test.ply")
    morphgs.save_spz(scene, tmp_path / "a.spz")
    morphgs.save_spz(scene, tmp_path / "b.spz", version=4)
    data = (tmp_path / "b.spz").read_bytes()
    magic, version, n, degree, fb, flags, streams, toc = struct.unpack_from("<IIIBBBBI", data)
    assert (magic, version, n, degree, flags, streams, toc) == (MAGIC, 4, 16, 3, 0, 6, 32)
    sizes = [struct.unpack_from("<QQ", data, 32 + 16 * i) for i in range(6)]
    assert [u for _, u in sizes] == [16 * 9, 16, 16 * 3, 16 * 3, 16 * 4, 16 * 45]
    assert 32 + 96 + sum(c for c, _ in sizes) == len(data)
    assert data[128:132] == b"\x28\xb5\x2f\xfd"  # zstd frame magic
    a, b = morphgs.load(tmp_path / "a.spz"), morphgs.load(tmp_path / "b.spz")
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    with pytest.raises(ValueError, match="version 5"):
        morphgs.save_spz(scene, tmp_path / "c.spz", version=5)


def test_spz_v4_of_a_degree_0_scene_has_five_streams(fixtures_dir: Path, tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / "splat-transform_minimal-v4.spz")
    morphgs.save_spz(scene, tmp_path / "m.spz", version=4)
    data = (tmp_path / "m.spz").read_bytes()
    assert data[15] == 5
    np.testing.assert_allclose(morphgs.load(tmp_path / "m.spz").means, scene.means, atol=2**-12)


def _v3_payload(scene: morphgs.GaussianScene, tmp_path: Path) -> bytes:
    morphgs.save_spz(scene, tmp_path / "p.spz")
    return gzip.decompress((tmp_path / "p.spz").read_bytes())


def _record(kind: int, payload: bytes) -> bytes:
    return struct.pack("<II", kind, len(payload)) + payload


def test_legacy_extension_records_follow_the_payload(fixtures_dir: Path, tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    raw = bytearray(_v3_payload(scene, tmp_path))
    raw[14] |= 0x2
    orbit = _record(0xADBE0002, struct.pack("<fff", -0.5, 1.2, 0.3))
    unknown = _record(0x12340001, b"\x01\x02\x03")
    p = tmp_path / "ext.spz"
    p.write_bytes(gzip.compress(bytes(raw) + orbit + unknown))
    with pytest.warns(morphgs.MorphgsWarning) as rec:
        s = morphgs.load(p)
    msgs = " | ".join(str(w.message) for w in rec)
    assert "safe_orbit_camera: elevation -0.5..1.2" in msgs
    assert "unknown .spz extension record 0x12340001 (3 bytes)" in msgs
    plain = morphgs.load(tmp_path / "p.spz")
    np.testing.assert_array_equal(s.means, plain.means)
    np.testing.assert_array_equal(s.sh_rest, plain.sh_rest)

    # a coordinate-system record: the same bytes said to be stored in RDF are not flipped
    raw_rdf = bytes(raw) + _record(0xADBE0003, struct.pack("<I", 6))
    p.write_bytes(gzip.compress(raw_rdf))
    as_rdf = morphgs.load(p)
    stored = morphgs.load(tmp_path / "p.spz", spz_axes="stored")
    np.testing.assert_array_equal(as_rdf.means, stored.means)
    np.testing.assert_array_equal(as_rdf.sh_rest, stored.sh_rest)

    # a record whose length runs past the stream
    p.write_bytes(gzip.compress(bytes(raw) + struct.pack("<II", 0x12340001, 1000) + b"xy"))
    with pytest.raises(morphgs.SceneFormatError, match="declares 1000 payload bytes"):
        morphgs.load(p)
    # a rotated coordinate system (RFD) cannot be converted, and says how to read it anyway
    p.write_bytes(gzip.compress(bytes(raw) + _record(0xADBE0003, struct.pack("<I", 10))))
    with pytest.raises(morphgs.SceneFormatError, match="RFD, a rotated coordinate system"):
        morphgs.load(p)
    with pytest.warns(morphgs.MorphgsWarning, match="stored in RFD"):
        morphgs.load(p, spz_axes="stored")


def test_v4_extension_zone(fixtures_dir: Path, tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    morphgs.save_spz(scene, tmp_path / "v4.spz", version=4)
    data = bytearray((tmp_path / "v4.spz").read_bytes())
    ext = _record(0xADBE0003, struct.pack("<I", 4))  # RUB: the default, stated explicitly
    data[14] |= 0x2
    struct.pack_into("<I", data, 16, 32 + len(ext))
    p = tmp_path / "v4ext.spz"
    p.write_bytes(bytes(data[:32]) + ext + bytes(data[32:]))
    np.testing.assert_array_equal(morphgs.load(p).means, morphgs.load(tmp_path / "v4.spz").means)


def test_spz_v1_float16_positions(tmp_path: Path) -> None:
    n = 5
    pos = np.array([[0.5, -1.25, 3.0], [100.0, 0.0, -0.001], [1, 2, 3], [4, 5, 6], [-7, 8, -9]],
                   np.float16)
    header = struct.pack("<IIIBBBB", MAGIC, 1, n, 0, 0, 0, 0)
    body = pos.tobytes() + bytes([255] * n) + bytes([128] * 3 * n) + bytes([160] * 3 * n)
    body += bytes([128, 128, 128] * n)  # v1/v2 rotations: x, y, z bytes
    p = tmp_path / "v1.spz"
    p.write_bytes(gzip.compress(header + body))
    s = morphgs.load(p, spz_axes="stored")
    np.testing.assert_array_equal(s.means, pos.astype(np.float32))
    np.testing.assert_allclose(s.log_scales, 0.0)


def test_compressed_ply_writer_round_trip(fixtures_dir: Path, tmp_path: Path) -> None:
    src = morphgs.load(fixtures_dir / "marcelpadilla_spot_10k.splat")
    out = tmp_path / "spot.compressed.ply"
    morphgs.save_compressed_ply(src, out)
    header = out.read_bytes()[:2000].split(b"end_header\n")[0].decode()
    assert "element chunk 40\n" in header and "element vertex 10000\n" in header
    assert header.index("min_x") < header.index("max_scale_z") < header.index("max_b")
    back = morphgs.load(out)
    assert len(back) == len(src)
    # Morton order changes the order: match each written splat to its source
    dist, idx = cKDTree(src.means).query(back.means)
    extent = np.ptp(src.means, axis=0).max()
    assert dist.max() < 2e-3 * extent
    assert len(np.unique(idx)) > 0.99 * len(src)
    np.testing.assert_allclose(back.colors, src.colors[idx], atol=1.5 / 255)
    np.testing.assert_allclose(back.opacities, src.opacities[idx], atol=1 / 255)
    dots = np.abs(np.sum(back.quats * src.quats[idx], axis=1))
    assert np.percentile(dots, 99) > 0.999
    # deterministic bytes
    morphgs.save_compressed_ply(src, tmp_path / "again.compressed.ply")
    assert (tmp_path / "again.compressed.ply").read_bytes() == out.read_bytes()


def test_compressed_ply_keeps_sh_to_degree_3(fixtures_dir: Path, tmp_path: Path) -> None:
    src = morphgs.load(fixtures_dir / "splatapult_test.ply")
    out = tmp_path / "t.compressed.ply"
    morphgs.save(src, out)
    back = morphgs.load(out)
    assert back.sh_degree == 3
    _, idx = cKDTree(src.means).query(back.means)
    np.testing.assert_allclose(back.sh_rest, np.clip(src.sh_rest[idx], -4, 4), atol=8 / 256)


def test_save_picks_the_writer_by_name(fixtures_dir: Path, tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    for name, first in [("a.PLY", b"ply\nformat binary_little_endian"), ("a.compressed.ply", b"ply"),
                        ("a.spz", b"\x1f\x8b"), ("a.glb", b"glTF")]:
        morphgs.save(scene, tmp_path / name)
        assert (tmp_path / name).read_bytes().startswith(first), name
    assert b"element chunk" in (tmp_path / "a.compressed.ply").read_bytes()[:400]
    morphgs.save(scene, tmp_path / "b.spz", spz_version=4)
    assert (tmp_path / "b.spz").read_bytes()[:8] == struct.pack("<II", MAGIC, 4)
    with pytest.raises(ValueError, match="unknown output extension '.obj'"):
        morphgs.save(scene, tmp_path / "a.obj")


def test_convert_cli_to_every_writer(fixtures_dir: Path, tmp_path: Path) -> None:
    src = fixtures_dir / "playcanvas_engine_monkey_0001.sog"
    for name, extra in [("m.glb", []), ("m.compressed.ply", []), ("m.spz", ["--spz-version", "4"])]:
        r = subprocess.run([sys.executable, "-m", "morphgs.cli", "convert", str(src),
                            str(tmp_path / name), *extra], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        assert "31,658 Gaussians" in r.stdout
        assert len(morphgs.load(tmp_path / name)) == 31658


def test_writers_give_the_same_bytes_on_one_thread(fixtures_dir: Path, tmp_path: Path) -> None:
    src = fixtures_dir / "marcelpadilla_spot_10k.splat"
    names = ["t.compressed.ply", "t.glb", "t.spz"]
    code = ("import sys, morphgs; s = morphgs.load(sys.argv[1]); "
            "[morphgs.save(s, f'{sys.argv[2]}/{n}', spz_version=4) for n in sys.argv[3:]]")
    one = tmp_path / "one"
    one.mkdir()
    env = {**os.environ, "RAYON_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", code, str(src), str(one), *names], check=True, env=env)
    scene = morphgs.load(src)
    for n in names:
        morphgs.save(scene, tmp_path / n, spz_version=4)
        assert (tmp_path / n).read_bytes() == (one / n).read_bytes(), n
