"""SceneSplat-7K/49K preprocessed folders: a folder made from a real PLY exactly as SceneSplat's
`scripts/preprocess_gs.py` makes it loads back to that PLY within the converter's loss (8-bit
truncated DC colour, no higher SH), with a MorphgsWarning saying so; lying or missing arrays fail
with SceneFormatError naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs

C0 = 0.28209479177387814


def _preprocess_gs(scene: morphgs.GaussianScene, out: Path) -> None:
    """`read_gaussian_attributes` + `process_ply_file` of unique1i/SceneSplat
    scripts/preprocess_gs.py, on the arrays the PLY holds."""
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "coord.npy", scene.means.astype(np.float32))
    np.save(out / "opacity.npy", (1 / (1 + np.exp(-scene.opacity_logits))).astype(np.float32))
    np.save(out / "scale.npy", np.exp(scene.log_scales).astype(np.float32))
    rots = scene.quats / (np.linalg.norm(scene.quats, axis=1, keepdims=True) + 1e-9)
    rots = rots * np.sign(rots[:, 0])[:, None]
    np.save(out / "quat.npy", rots.astype(np.float32))
    color = np.clip((scene.sh0 * C0).astype(np.float32) + 0.5, 0, 1)
    np.save(out / "color.npy", (color * 255).astype(np.uint8))


def test_folder_from_the_scenesplat_converter(fixtures_dir: Path, tmp_path: Path) -> None:
    ply = morphgs.load(fixtures_dir / "splatapult_test.ply")
    folder = tmp_path / "scene0000_00"
    _preprocess_gs(ply, folder)
    with pytest.warns(morphgs.MorphgsWarning, match="SceneSplat .* SH degree 0, which is lossy"):
        s = morphgs.load(folder)
    assert s.sh_degree == 0 and len(s) == len(ply)
    np.testing.assert_array_equal(s.means, ply.means)
    np.testing.assert_allclose(s.log_scales, ply.log_scales, atol=1e-5)
    np.testing.assert_allclose(s.opacities, ply.opacities, atol=1e-6)
    dots = np.abs(np.sum(s.quats * ply.quats, axis=1))
    np.testing.assert_allclose(dots, 1, atol=1e-6)
    # colours: the middle of each truncated 8-bit bucket, so within half a step of the PLY's
    np.testing.assert_allclose(s.colors, np.clip(0.5 + C0 * ply.sh0, 0, 1), atol=0.5 / 255 + 1e-6)


def test_optional_normals_and_other_dtypes(fixtures_dir: Path, tmp_path: Path) -> None:
    ply = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    folder = tmp_path / "s"
    _preprocess_gs(ply, folder)
    np.save(folder / "normal.npy", np.zeros((3, 3), np.float32))
    np.save(folder / "opacity.npy", np.load(folder / "opacity.npy").astype(np.float64)[:, None])
    np.save(folder / "coord.npy", np.asfortranarray(np.load(folder / "coord.npy")))
    with pytest.warns(morphgs.MorphgsWarning):
        s = morphgs.load(folder)
    np.testing.assert_array_equal(s.means, ply.means)
    np.testing.assert_allclose(s.opacities, ply.opacities, atol=1e-6)


def test_malformed_scenesplat_folders(fixtures_dir: Path, tmp_path: Path) -> None:
    ply = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    folder = tmp_path / "s"

    def expect(pattern: str, file: str) -> None:
        with pytest.raises(morphgs.SceneFormatError, match=pattern) as e:
            morphgs.load(folder)
        assert e.value.path.endswith(file)

    _preprocess_gs(ply, folder)
    (folder / "quat.npy").unlink()
    expect("quat.npy is missing", "s")

    _preprocess_gs(ply, folder)
    np.save(folder / "scale.npy", np.ones((4, 3), np.float32))
    expect(r"shape \[4, 3\], expected \(3, 3\)", "scale.npy")

    _preprocess_gs(ply, folder)
    data = bytearray((folder / "coord.npy").read_bytes())
    at = data.find(b"(3, 3)")
    data[at : at + 6] = b"(9, 3)"  # the header lies about the shape
    (folder / "coord.npy").write_bytes(bytes(data))
    expect(r"declares shape \[9, 3\] of <f4 \(108 bytes\) but 36 bytes follow", "coord.npy")

    _preprocess_gs(ply, folder)
    with open(folder / "color.npy", "wb") as f:  # a trillion rows claimed, 9 bytes present
        np.lib.format.write_array_header_1_0(
            f, {"descr": "|u1", "fortran_order": False, "shape": (10**12, 3)})
        f.write(bytes(9))
    expect(r"declares shape \[1000000000000, 3\] of \|u1 .* but 9 bytes follow", "color.npy")

    _preprocess_gs(ply, folder)
    np.save(folder / "color.npy", np.full((3, 3), 300.0, np.float32))
    expect("outside the 0-255 colour range", "color.npy")

    _preprocess_gs(ply, folder)
    np.save(folder / "quat.npy", np.zeros((3, 4), np.complex64))
    expect("dtype <c8 is not supported", "quat.npy")

    (folder / "coord.npy").write_bytes(b"not an npy")
    expect("not a NumPy .npy file", "coord.npy")


def test_a_folder_that_is_no_scene(tmp_path: Path) -> None:
    with pytest.raises(IsADirectoryError, match="neither a SceneSplat"):
        morphgs.load(tmp_path)


def test_curation_discovers_scene_folders(fixtures_dir: Path, tmp_path: Path) -> None:
    from morphgs.curation.sources import discover

    folder = tmp_path / "scene0000_00"
    _preprocess_gs(morphgs.load(fixtures_dir / "metalsplatter_train3.ply"), folder)
    sources, problems = discover([folder, fixtures_dir / "playcanvas_engine_playbot_lod6"])
    assert problems == []
    assert [s.path for s in sources] == [str(folder), str(fixtures_dir / "playcanvas_engine_playbot_lod6")]
