"""Malformed .spz / .splat / compressed PLY files fail with SceneFormatError naming the file and
the problem — before any large allocation, never with a panic or a hang."""

from __future__ import annotations

import gzip
import struct
from collections.abc import Callable
from pathlib import Path

import pytest

import morphgs


def _expect(path: Path, pattern: str) -> morphgs.SceneFormatError:
    with pytest.raises(morphgs.SceneFormatError, match=pattern) as e:
        morphgs.load(path)
    assert str(path) in str(e.value)
    assert e.value.path == str(path)
    return e.value


def _spz_header(version: int, count: int, degree: int = 0, fb: int = 12, flags: int = 0) -> bytes:
    return struct.pack("<IIIBBBB", 0x5053474E, version, count, degree, fb, flags, 0)


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


def test_truncated_gzip_stream(fixtures_dir: Path, tmp_path: Path) -> None:
    data = (fixtures_dir / "metalsplatter_train3.spz").read_bytes()
    p = _write(tmp_path, "cut.spz", data[: len(data) - 12])
    _expect(p, "gzip stream: corrupt or truncated compressed data")
    p = _write(tmp_path, "cut_header.spz", data[:15])
    _expect(p, "corrupt or truncated before the SPZ header|SPZ header is 16 bytes")


def test_corrupt_gzip_crc(fixtures_dir: Path, tmp_path: Path) -> None:
    data = bytearray((fixtures_dir / "metalsplatter_train3.spz").read_bytes())
    data[-6] ^= 0xFF  # inside the CRC32 trailer
    _expect(_write(tmp_path, "crc.spz", bytes(data)), "corrupt or truncated")


def test_wrong_magic_inside_gzip_and_unknown_version(tmp_path: Path) -> None:
    bad = gzip.compress(b"XGSP" + _spz_header(3, 1)[4:] + bytes(20))
    _expect(_write(tmp_path, "magic.spz", bad), r"not an SPZ stream: magic 0x50534758")
    _expect(_write(tmp_path, "v9.spz", gzip.compress(_spz_header(9, 1) + bytes(20))),
            "unsupported SPZ version 9")
    _expect(_write(tmp_path, "deg.spz", gzip.compress(_spz_header(3, 1, degree=7) + bytes(20))),
            "SH degree 7")


def test_counts_beyond_the_data(tmp_path: Path) -> None:
    # gzip: a count no deflate stream of this size could hold is refused before inflating
    huge = gzip.compress(_spz_header(3, 4_000_000_000) + bytes(100))
    _expect(_write(tmp_path, "huge.spz", huge), "declares 4000000000 points .* can hold at most")
    # gzip: a plausible count that the stream does not hold
    short = gzip.compress(_spz_header(3, 1000) + bytes(100))
    _expect(_write(tmp_path, "short.spz", short), "truncated: the SPZ header declares 1000 points")
    # plain (uncompressed) v2
    raw = _spz_header(2, 1_000_000_000, fb=8) + bytes(19)
    _expect(_write(tmp_path, "raw.spz", raw), "declares 1000000000 points needing")


def test_lying_header_with_fewer_points_than_data(tmp_path: Path) -> None:
    data = _spz_header(3, 1) + bytes(20 * 3)
    _expect(_write(tmp_path, "lie.spz", gzip.compress(data)),
            "gzip stream holds more data than the 1 points the SPZ header declares")
    _expect(_write(tmp_path, "lie_raw.spz", data), "40 bytes beyond the 1 points")


def _v4(tmp_path: Path, fixtures_dir: Path, edit: Callable[[bytearray], bytes]) -> Path:
    data = bytearray((fixtures_dir / "splat-transform_minimal-v4.spz").read_bytes())
    return _write(tmp_path, "v4.spz", edit(data))


def test_spz_v4_truncated_and_corrupt_zstd(fixtures_dir: Path, tmp_path: Path) -> None:
    # file cut inside the last stream
    _expect(_v4(tmp_path, fixtures_dir, lambda d: bytes(d[:-5])),
            "truncated: SPZ v4 stream 'rotations' needs bytes")

    # last zstd frame cut short, with the table of contents agreeing: the frame itself is short
    def shorten_last_frame(d: bytearray) -> bytes:
        toc, last = 32, 4
        size = struct.unpack_from("<Q", d, toc + 16 * last)[0]
        struct.pack_into("<Q", d, toc + 16 * last, size - 3)
        return bytes(d[:-3])

    _expect(_v4(tmp_path, fixtures_dir, shorten_last_frame),
            "SPZ v4 stream 'rotations': (corrupt or truncated|zstd data decompresses to)")

    # a stream whose frame is not zstd at all
    def clobber_first_frame(d: bytearray) -> bytes:
        d[32 + 16 * 5 : 32 + 16 * 5 + 4] = b"\x00\x00\x00\x00"
        return bytes(d)

    _expect(_v4(tmp_path, fixtures_dir, clobber_first_frame), "SPZ v4 stream 'positions'")


def test_spz_v4_lying_table_of_contents(fixtures_dir: Path, tmp_path: Path) -> None:
    def wrong_plain_size(d: bytearray) -> bytes:
        struct.pack_into("<Q", d, 32 + 8, 10**12)
        return bytes(d)

    _expect(_v4(tmp_path, fixtures_dir, wrong_plain_size),
            "stream 'positions' declares 1000000000000 bytes but 4 points need 36")

    def more_points(d: bytearray) -> bytes:
        struct.pack_into("<I", d, 8, 2_000_000_000)
        return bytes(d)

    _expect(_v4(tmp_path, fixtures_dir, more_points), "2000000000 points need")

    def toc_outside(d: bytearray) -> bytes:
        struct.pack_into("<I", d, 16, 1 << 30)
        return bytes(d)

    _expect(_v4(tmp_path, fixtures_dir, toc_outside), "table of contents at byte 1073741824")

    def stream_count(d: bytearray) -> bytes:
        d[15] = 9
        return bytes(d)

    _expect(_v4(tmp_path, fixtures_dir, stream_count), "declares 9 streams")
    _expect(_v4(tmp_path, fixtures_dir, lambda d: bytes(d) + b"junk"), "4 bytes after the last")


def test_splat_sized_garbage_is_not_a_scene(tmp_path: Path) -> None:
    nan_scale = struct.pack("<6f", 0, 0, 0, float("nan"), 1, 1) + bytes(8)
    _expect(_write(tmp_path, "nan.splat", nan_scale * 4), "as an antimatter15 .splat record 0")
    _expect(_write(tmp_path, "odd.splat", bytes(33)), "unrecognised scene format")
    _expect(_write(tmp_path, "empty.splat", b""), "the file is empty")


def _edit_header(fixtures_dir: Path, old: bytes, new: bytes) -> bytes:
    data = (fixtures_dir / "playcanvas_engine_test.compressed.ply").read_bytes()
    end = data.index(b"end_header\n")
    assert old in data[:end]
    return data[:end].replace(old, new) + data[end:]


def test_compressed_ply_counts_beyond_the_data(fixtures_dir: Path, tmp_path: Path) -> None:
    p = _write(tmp_path, "c.ply", _edit_header(fixtures_dir, b"element vertex 64", b"element vertex 99999999"))
    e = _expect(p, "element 'vertex': the header declares 99999999 rows")
    assert e.element == "vertex"
    p = _write(tmp_path, "c2.ply", _edit_header(fixtures_dir, b"element chunk 1", b"element chunk 2"))
    _expect(p, "element 'chunk'|remain")
    data = (fixtures_dir / "playcanvas_engine_test.compressed.ply").read_bytes()
    _expect(_write(tmp_path, "cut.ply", data[:-100]), "element 'sh': the header declares 64 rows")


def test_compressed_ply_inconsistent_elements(fixtures_dir: Path, tmp_path: Path) -> None:
    # 60 splats still need one chunk, but the sh element keeps 64 rows
    p = _write(tmp_path, "c.ply", _edit_header(fixtures_dir, b"element vertex 64", b"element vertex 60"))
    _expect(p, "element 'sh': 64 rows for 60 splats")
    p = _write(tmp_path, "d.ply", _edit_header(
        fixtures_dir, b"property uint packed_rotation", b"property float packed_rotation"))
    _expect(p, "property 'packed_rotation': is F32; the packed fields must be uint32")
