"""The frame writers. Float EXR files (depth and alpha maps, `_write_exr_batch`) read back bit for bit
by our reader and by the official OpenEXR library (the `OpenEXR` package of the Academy Software
Foundation), whatever the channel count, the size (not a multiple of the 16-line ZIP chunk) and the
special values. PNGs written from float32 colour hold `Render.to_uint8`'s bytes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import _core

OpenEXR = pytest.importorskip("OpenEXR")

NAMES = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}


def _awkward(shape: tuple[int, ...], seed: int) -> np.ndarray:
    """Smooth ramps mixed with NaN (with payloads), +-inf, -0.0, subnormals and arbitrary bits."""
    rng = np.random.default_rng(seed)
    out = (1.5 + np.cumsum(rng.random(shape, dtype=np.float32), axis=-1) * 1e-3).astype(np.float32)
    bits = out.reshape(-1).view(np.uint32)
    n = bits.size
    pick = rng.random(n)
    bits[pick < 0.05] = np.uint32(0x7FC00000)  # NaN
    bits[(pick >= 0.05) & (pick < 0.08)] = np.uint32(0x7FC01234)  # NaN with a payload
    bits[(pick >= 0.08) & (pick < 0.10)] = np.uint32(0x7F800000)  # +inf
    bits[(pick >= 0.10) & (pick < 0.12)] = np.uint32(0xFF800000)  # -inf
    bits[(pick >= 0.12) & (pick < 0.14)] = np.uint32(0x80000000)  # -0.0
    sub = (pick >= 0.14) & (pick < 0.16)
    bits[sub] = rng.integers(1, 0x7FFFFF, int(sub.sum()), dtype=np.uint32)  # subnormals
    wild = (pick >= 0.16) & (pick < 0.30)
    bits[wild] = rng.integers(0, 2**32, int(wild.sum()), dtype=np.uint32)  # any pattern
    return out


def _openexr_channels(path: Path) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    with OpenEXR.File(str(path), separate_channels=True) as f:
        header = dict(f.header())
        return {name: np.array(c.pixels) for name, c in f.channels().items()}, header


@pytest.mark.parametrize("channels", [1, 3, 4, 5, 12])
@pytest.mark.parametrize("size", [(1, 1), (13, 37), (64, 16), (9, 33)])
def test_exr_reads_back_bit_exact_in_openexr_and_our_reader(tmp_path: Path, channels: int,
                                                            size: tuple[int, int]) -> None:
    w, h = size
    shape = (h, w) if channels == 1 else (h, w, channels)
    data = _awkward(shape, seed=channels * 100 + w)
    path = tmp_path / "a.exr"
    _core._write_exr(path, data)

    (ours,) = _core._read_exr_batch([path])
    assert ours.dtype == np.float32 and ours.shape == data.shape
    np.testing.assert_array_equal(ours.view(np.uint32), data.view(np.uint32))

    planes, header = _openexr_channels(path)
    names = NAMES.get(channels, [f"C{i}" for i in range(channels)])
    assert sorted(planes) == sorted(names)
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    assert tuple(header["dataWindow"][1]) == (w - 1, h - 1)
    for i, name in enumerate(names):
        want = data if channels == 1 else data[..., i]
        got = planes[name]
        assert got.dtype == np.float32 and got.shape == (h, w), name
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32), err_msg=name)


def test_rendered_depth_and_alpha_maps_read_back_in_openexr(tmp_path: Path) -> None:
    scene = morphgs.synthetic.scene(n_gaussians=3000, sh_degree=1, seed=3)
    o = morphgs.synthetic.suggested_orbit()
    cams = morphgs.trajectory.orbit(o.center, o.radius, o.height - o.center[2], 2, fov_y_degrees=50.0,
                                    resolution=(70, 41))
    r = morphgs.render(scene, cams)
    r.save(tmp_path / "out")
    for i in range(2):
        for name, want in (("depth", r.depth[i]), ("alpha", r.alpha[i])):
            planes, _ = _openexr_channels(tmp_path / "out" / f"{i:05d}.{name}.exr")
            assert list(planes) == ["Y"]
            np.testing.assert_array_equal(planes["Y"].view(np.uint32), want.view(np.uint32))


def test_exr_batches_are_the_same_bytes_as_single_frames(tmp_path: Path) -> None:
    frames = _awkward((5, 20, 17), seed=9)
    paths = [tmp_path / f"{i}.exr" for i in range(5)]
    _core._write_exr_batch(paths, frames)
    for i, p in enumerate(paths):
        one = tmp_path / f"one{i}.exr"
        _core._write_exr(one, frames[i])
        assert one.read_bytes() == p.read_bytes()


def _float_colour(shape: tuple[int, ...], seed: int) -> np.ndarray:
    """Colour in and out of [0, 1], +-inf, -0.0, and every float whose product with 255 is an exact
    tie k + 0.5 (where round-half-even and round-half-away differ for even k)."""
    rng = np.random.default_rng(seed)
    rgb = rng.uniform(-0.2, 1.2, shape).astype(np.float32)
    flat = rgb.reshape(-1)
    k = np.arange(255, dtype=np.float32)
    cand = ((k + np.float32(0.5)) / np.float32(255)).astype(np.float32)
    cand = np.concatenate([cand, np.nextafter(cand, np.float32(0)), np.nextafter(cand, np.float32(1))])
    ties = cand[cand * np.float32(255) == np.floor(cand * np.float32(255)) + np.float32(0.5)]
    assert ties.size > 50
    flat[: ties.size] = ties
    flat[ties.size: ties.size + 4] = [np.inf, -np.inf, -0.0, 1.0]
    return rgb


def test_pngs_from_float_colour_hold_to_uint8s_bytes(tmp_path: Path) -> None:
    from PIL import Image

    rgb = _float_colour((3, 11, 29, 3), seed=4)
    want = morphgs.Render(rgb, rgb[..., 0], rgb[..., 0], {}).to_uint8()
    paths = [tmp_path / f"{i}.png" for i in range(3)]
    _core._write_png_batch(paths, rgb)
    for i, p in enumerate(paths):
        np.testing.assert_array_equal(np.asarray(Image.open(p)), want[i])
    # the same bytes as writing the uint8 frames
    _core._write_png_batch([tmp_path / "u8.png"], want[:1])
    assert (tmp_path / "u8.png").read_bytes() == paths[0].read_bytes()
    _core._write_png(tmp_path / "one.png", rgb[2])
    assert (tmp_path / "one.png").read_bytes() == paths[2].read_bytes()
    with pytest.raises(TypeError, match="uint8 or float32"):
        _core._write_png_batch([tmp_path / "x.png"], rgb[:1].astype(np.float64))
