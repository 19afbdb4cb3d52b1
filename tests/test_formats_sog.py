"""PlayCanvas SOG: real files written by splat-transform (tests/fixtures/ATTRIBUTION.md) decode as
an independent NumPy + libwebp decoder (tests/sog_reference.py) says, bundled, unbundled and
re-zipped; legacy v1 is checked on a file built to its published layout."""

from __future__ import annotations

import io
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

import morphgs
import sog_reference

MONKEY = "playcanvas_engine_monkey_0001.sog"
PLAYBOT = "playcanvas_engine_playbot_lod6"


def _assert_matches(scene: morphgs.GaussianScene, ref: dict[str, np.ndarray]) -> None:
    assert len(scene) == len(ref["means"])
    np.testing.assert_allclose(scene.means, ref["means"], rtol=1e-5, atol=1e-6)
    q = ref["quats"] / np.linalg.norm(ref["quats"], axis=1, keepdims=True)
    np.testing.assert_allclose(scene.quats, q, atol=2e-6)
    np.testing.assert_allclose(scene.log_scales, ref["log_scales"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(scene.sh0, ref["sh0"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(scene.opacity_logits, ref["opacity_logits"], rtol=1e-5, atol=1e-5)
    if "sh_rest" in ref:
        np.testing.assert_allclose(scene.sh_rest, ref["sh_rest"], rtol=1e-6, atol=1e-6)


def test_bundled_sog_from_splat_transform(fixtures_dir: Path) -> None:
    path = fixtures_dir / MONKEY
    scene = morphgs.load(path)
    assert len(scene) == 31658 and scene.sh_degree == 0
    _assert_matches(scene, sog_reference.decode(sog_reference.zip_loader(path)))
    # meta.json bounds are log-transformed: sign(x) ln(|x| + 1); x spans them exactly
    lo, hi = scene.bounds()
    np.testing.assert_allclose(np.sign(lo) * np.log1p(np.abs(lo)), [-0.84535, -0.66229, -0.57564],
                               atol=1e-4)
    np.testing.assert_allclose(np.sign(hi) * np.log1p(np.abs(hi)), [0.84535, 0.67896, 0.60028],
                               atol=1e-4)


def test_unbundled_sog_with_sh_bands(fixtures_dir: Path) -> None:
    folder = fixtures_dir / PLAYBOT
    scene = morphgs.load(folder)
    assert len(scene) == 1873 and scene.sh_degree == 2  # meta.json: "bands": 2
    ref = sog_reference.decode(sog_reference.dir_loader(folder))
    _assert_matches(scene, ref)
    assert np.abs(scene.sh_rest).max() > 0.05  # the palette really is decoded
    via_meta = morphgs.load(folder / "meta.json")
    np.testing.assert_array_equal(via_meta.sh_rest, scene.sh_rest)


def test_deflated_zip_of_the_folder_reads_the_same(fixtures_dir: Path, tmp_path: Path) -> None:
    folder = fixtures_dir / PLAYBOT
    out = tmp_path / "playbot.sog"
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for f in sorted(folder.iterdir()):
            z.write(f, f"playbot/{f.name}")  # one folder level inside the archive
    a, b = morphgs.load(folder), morphgs.load(out)
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.sh_rest, b.sh_rest)


def test_legacy_v1_sog(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 37
    means = rng.normal(0, 2, (n, 3))
    log_scales = rng.uniform(-6, -1, (n, 3))
    quats = rng.normal(size=(n, 4))
    sh0 = rng.normal(0, 1, (n, 3))
    opacity = rng.normal(0, 2, n)
    files = sog_reference.encode_v1(means, log_scales, quats, sh0, opacity)
    folder = tmp_path / "v1"
    folder.mkdir()
    for name, data in files.items():
        (folder / name).write_bytes(data)
    scene = morphgs.load(folder)
    _assert_matches(scene, sog_reference.decode(sog_reference.dir_loader(folder)))
    # and close to what was encoded (16-bit log positions, 8-bit linear ranges)
    np.testing.assert_allclose(scene.means, means, atol=2e-3 * np.abs(means).max())
    np.testing.assert_allclose(scene.sh0, sh0, atol=(sh0.max() - sh0.min()) / 255)
    qn = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    assert np.all(np.abs(np.sum(scene.quats * qn, axis=1)) > 0.999)


def test_sog_converts_to_the_web_formats(fixtures_dir: Path, tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / PLAYBOT)
    for name in ("p.compressed.ply", "p.glb", "p.spz"):
        morphgs.save(scene, tmp_path / name, spz_version=4)
        back = morphgs.load(tmp_path / name)
        assert len(back) == len(scene) and back.sh_degree == 2, name


def _bundle(folder: Path, edit: dict[str, bytes | None]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for f in sorted(folder.iterdir()):
            data = edit.get(f.name, f.read_bytes())
            if data is not None:
                z.writestr(f.name, data)
    return buf.getvalue()


def test_malformed_sog(fixtures_dir: Path, tmp_path: Path) -> None:
    folder = fixtures_dir / PLAYBOT
    meta = (folder / "meta.json").read_text()

    def expect(data: bytes, pattern: str) -> None:
        p = tmp_path / "bad.sog"
        p.write_bytes(data)
        with pytest.raises(morphgs.SceneFormatError, match=pattern) as e:
            morphgs.load(p)
        assert str(p) in str(e.value)

    good = (fixtures_dir / MONKEY).read_bytes()
    expect(good[: len(good) // 2], "end-of-central-directory")
    expect(_bundle(folder, {"meta.json": None}), "ZIP archive without a SOG meta.json")
    expect(_bundle(folder, {"meta.json": meta.replace('"count":1873', '"count":99999').encode()}),
           "texture is .* texels")
    expect(_bundle(folder, {"meta.json": meta.replace('"quats"', '"quatz"').encode()}),
           "quats.files.*missing")
    expect(_bundle(folder, {"sh0.webp": None}), "sh0.webp.*not in the archive")
    expect(_bundle(folder, {"scales.webp": b"RIFF\x00\x00\x00\x00WEBPjunk"}), "WebP")
    expect(_bundle(folder, {"meta.json": b"{not json"}), "not valid JSON")
    expect(_bundle(folder, {"meta.json": meta.replace('"version":2', '"version":7').encode()}),
           "SOG version 7")
    bad_crc = bytearray(_bundle(folder, {}))
    at = bad_crc.find(b"RIFF")
    bad_crc[at + 40] ^= 0xFF
    expect(bytes(bad_crc), "CRC-32 mismatch|WebP")


def test_sog_folder_with_a_missing_texture(fixtures_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "sog"
    shutil.copytree(fixtures_dir / PLAYBOT, folder)
    (folder / "quats.webp").unlink()
    with pytest.raises(FileNotFoundError):
        morphgs.load(folder)
