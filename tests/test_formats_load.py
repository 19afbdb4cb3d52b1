"""Reading .splat, .spz (v2/v3/v4/raw) and SuperSplat compressed PLY files written by other tools.

Fixtures: tests/fixtures (see its ATTRIBUTION.md): metalsplatter_train3.{ply,splat,spz} are
the same three real splats in three formats; splat-transform_minimal* are four splats in every
.splat/.spz variant; playcanvas_engine_*.compressed.ply are SuperSplat files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs

C0 = 0.28209479177387814
SPZ_COLOR_STEP = C0 / (0.15 * 255)  # one .spz colour byte, in linear colour units
SCENE_SUFFIXES = (".ply", ".splat", ".spz")


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def _quat_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.sum(a.astype(np.float64) * b, axis=1))


def _covariances(s: morphgs.GaussianScene) -> np.ndarray:
    w, x, y, z = s.quats.astype(np.float64).T
    r = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=1).reshape(-1, 3, 3)
    m = r * s.scales.astype(np.float64)[:, None, :]
    return m @ m.transpose(0, 2, 1)


def test_every_scene_fixture_loads_and_the_points_file_is_refused(fixtures_dir: Path) -> None:
    scene_files = sorted(p for p in fixtures_dir.iterdir() if p.name.endswith(SCENE_SUFFIXES))
    assert len(scene_files) == 12
    for p in scene_files:
        s = morphgs.load(p)
        assert len(s) > 0, p.name
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest"):
            assert np.isfinite(getattr(s, name)).all(), (p.name, name)
        np.testing.assert_allclose(np.linalg.norm(s.quats, axis=1), 1.0, atol=1e-5)
    # gsplat_test_garden.npz holds points and cameras, not Gaussians: it is no scene format.
    npz = fixtures_dir / "gsplat_test_garden.npz"
    with pytest.raises(morphgs.SceneFormatError, match="unrecognised scene format") as e:
        morphgs.load(npz)
    assert str(npz) in str(e.value)


def test_metalsplatter_splat_matches_the_ply_within_8_bit_colour(fixtures_dir: Path) -> None:
    ply = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    spl = morphgs.load(fixtures_dir / "metalsplatter_train3.splat")
    assert len(spl) == len(ply) == 3 and spl.sh_degree == 0
    np.testing.assert_array_equal(spl.means, ply.means)  # float32 in both
    np.testing.assert_allclose(spl.log_scales, ply.log_scales, atol=1e-5)
    assert (_quat_dots(spl.quats, ply.quats) >= 0.9999).all()
    # one 8-bit bucket (MetalSplatter's encoder truncates rather than rounds)
    assert np.abs(spl.colors - ply.colors).max() <= 1 / 255 + 1e-6
    assert np.abs(_sigmoid(spl.opacity_logits) - _sigmoid(ply.opacity_logits)).max() <= 1 / 255


def test_metalsplatter_spz_matches_the_ply_after_rub_to_rdf(fixtures_dir: Path) -> None:
    ply = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    spz = morphgs.load(fixtures_dir / "metalsplatter_train3.spz")
    assert len(spz) == 3 and spz.sh_degree == ply.sh_degree == 3
    # 24-bit fixed point with 12 fractional bits: half a step
    assert np.abs(spz.means - ply.means).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(spz.log_scales - ply.log_scales).max() <= 0.5 / 16 + 1e-6
    assert (_quat_dots(spz.quats, ply.quats) >= 0.9999).all()
    assert np.abs(spz.colors - ply.colors).max() <= 0.5 * SPZ_COLOR_STEP + 1e-6
    assert np.abs(_sigmoid(spz.opacity_logits) - _sigmoid(ply.opacity_logits)).max() <= 0.5 / 255
    # SH: the reference encoder keeps 5 bits for band 1 and 4 for the rest (buckets of 8 and 16
    # on a 1/128 grid); each coefficient lies within half a bucket plus one grid step.
    err = np.abs(spz.sh_rest - ply.sh_rest)
    assert err[:, :3].max() <= 4 / 128 + 1 / 128
    assert err[:, 3:].max() <= 8 / 128 + 1 / 128
    # the sign flips matter: without the conversion, odd coefficients disagree
    stored = morphgs.load(fixtures_dir / "metalsplatter_train3.spz", spz_axes="stored")
    np.testing.assert_allclose(stored.means[:, 1:], -spz.means[:, 1:])
    np.testing.assert_allclose(stored.means[:, 0], spz.means[:, 0])
    np.testing.assert_allclose(stored.quats[:, 2:], -spz.quats[:, 2:])
    np.testing.assert_allclose(stored.sh_rest[:, 0], -spz.sh_rest[:, 0])  # basis y: odd
    np.testing.assert_allclose(stored.sh_rest[:, 2], spz.sh_rest[:, 2])  # basis x: even


def test_splat_transform_variants_decode_to_the_same_splats(fixtures_dir: Path) -> None:
    base = fixtures_dir / "splat-transform_minimal"
    splat = morphgs.load(f"{base}.splat")
    v3 = morphgs.load(f"{base}-v3.spz")
    v4 = morphgs.load(f"{base}-v4.spz")
    # v3 (gzip) and v4 (zstd) were written by @adobe/spz from the same cloud: identical decode
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh0"):
        np.testing.assert_array_equal(getattr(v3, name), getattr(v4, name), err_msg=name)
    # ... and equal to the .splat within SPZ quantisation (converted from RUB to RDF)
    np.testing.assert_allclose(v4.means, splat.means, atol=0.5 / 4096)
    np.testing.assert_allclose(v4.log_scales, splat.log_scales, atol=0.5 / 16)
    assert np.abs(v4.colors - splat.colors).max() <= 0.5 * SPZ_COLOR_STEP + 1e-6
    np.testing.assert_allclose(v4.opacity_logits, splat.opacity_logits, atol=1e-5)
    # the .splat stores rotation bytes (0,0,0,1) and the .spz the identity; the scales are
    # isotropic, so the Gaussians (their covariances) are the same
    np.testing.assert_allclose(_covariances(v4), _covariances(splat), rtol=0.07, atol=1e-7)

    # minimal-v2.spz is gzip(minimal-raw.spz), both hand-written by splat-transform's fixture
    # script ("historical non-spec"): stored without axis conversion, colour bytes = RGB*255.
    raw = morphgs.load(f"{base}-raw.spz", spz_axes="stored")
    v2 = morphgs.load(f"{base}-v2.spz", spz_axes="stored")
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh0"):
        np.testing.assert_array_equal(getattr(raw, name), getattr(v2, name), err_msg=name)
    np.testing.assert_allclose(v2.means, splat.means, atol=0.5 / 256)  # 8 fractional bits
    np.testing.assert_allclose(v2.log_scales, splat.log_scales, atol=0.5 / 16)
    np.testing.assert_allclose(v2.opacity_logits, splat.opacity_logits, atol=1e-5)
    np.testing.assert_allclose(_covariances(v2), _covariances(splat), rtol=0.07, atol=1e-7)
    colour_bytes = v2.sh0 * 0.15 + 0.5  # what the decoder undid: byte/255
    np.testing.assert_allclose(colour_bytes, splat.colors, atol=1e-6)


def test_compressed_ply_with_sh_decodes_within_its_chunk_bounds(fixtures_dir: Path) -> None:
    s = morphgs.load(fixtures_dir / "playcanvas_engine_test.compressed.ply")
    assert len(s) == 64 and s.sh_degree == 3
    # SH bytes map to (v/256 - 0.5) * 8, in [-4, 4]
    assert np.abs(s.sh_rest).max() <= 4.0
    assert np.ptp(s.sh_rest) > 0
    lo, hi = s.bounds()
    assert (hi - lo > 0).all()


def test_guitar_compressed_ply_has_sane_statistics(fixtures_dir: Path) -> None:
    s = morphgs.load(fixtures_dir / "playcanvas_engine_guitar.compressed.ply")
    assert len(s) == 90_854 and s.sh_degree == 0
    lo, hi = s.bounds()
    extent = hi - lo
    assert (extent > 0.5).all() and (extent < 10).all(), extent
    scales = s.scales.max(axis=1)
    assert 1e-4 < np.median(scales) < 0.05, np.median(scales)
    assert np.percentile(scales, 99) < 0.5
    op = s.opacities
    assert 0 < op.min() and op.max() < 1
    assert 0.05 < np.median(op) < 0.95
    # SuperSplat's per-chunk colour bounds allow a few colours outside [0, 1] (SH-free capture)
    p1, p50, p99 = np.percentile(s.colors, [1, 50, 99])
    assert -0.1 < p1 and p99 < 1.25 and 0.1 < p50 < 0.9
    # positions cluster: most splats lie within the central 98% box
    q = np.percentile(s.means, [1, 99], axis=0)
    inside = ((s.means >= q[0]) & (s.means <= q[1])).all(axis=1).mean()
    assert inside > 0.9


def test_detection_uses_content_not_extension(fixtures_dir: Path, tmp_path: Path) -> None:
    for src, name in [
        ("metalsplatter_train3.spz", "scene.ply"),
        ("metalsplatter_train3.splat", "scene.spz"),
        ("playcanvas_engine_test.compressed.ply", "scene.bin"),
        ("splat-transform_minimal-v4.spz", "scene"),
    ]:
        ref = morphgs.load(fixtures_dir / src)
        dst = tmp_path / name
        dst.write_bytes((fixtures_dir / src).read_bytes())
        got = morphgs.load(dst)
        np.testing.assert_array_equal(got.means, ref.means)


def test_spz_axes_rejects_unknown_values(fixtures_dir: Path) -> None:
    with pytest.raises(ValueError, match="spz_axes must be 'rdf' or 'stored'"):
        morphgs.load(fixtures_dir / "metalsplatter_train3.spz", spz_axes="rub")


def test_decoding_and_encoding_are_identical_for_any_thread_count(fixtures_dir: Path) -> None:
    import os
    import subprocess
    import sys

    script = (
        "import hashlib, sys, tempfile, os, morphgs\n"
        "h = hashlib.sha256()\n"
        "for f in sys.argv[1:]:\n"
        "    s = morphgs.load(f)\n"
        "    for a in (s.means, s.quats, s.log_scales, s.opacity_logits, s.sh0, s.sh_rest):\n"
        "        h.update(a.tobytes())\n"
        "    with tempfile.TemporaryDirectory() as d:\n"
        "        for ext, save in (('.spz', morphgs.save_spz), ('.splat', morphgs.save_splat)):\n"
        "            p = os.path.join(d, 'x' + ext)\n"
        "            save(s, p)\n"
        "            h.update(open(p, 'rb').read())\n"
        "print(h.hexdigest(), morphgs.num_threads())\n"
    )
    files = [str(fixtures_dir / f) for f in (
        "playcanvas_engine_guitar.compressed.ply", "marcelpadilla_spot_10k.splat",
        "splat-transform_minimal-v4.spz", "metalsplatter_train3.spz")]
    out = {}
    for threads in ("1", "3"):
        env = dict(os.environ, RAYON_NUM_THREADS=threads)
        r = subprocess.run([sys.executable, "-c", script, *files], env=env, check=True,
                           capture_output=True, text=True)
        digest, used = r.stdout.split()
        assert used == threads
        out[threads] = digest
    assert out["1"] == out["3"]
