"""PNG frames through the native decoder: the same pixels as Pillow for every common PNG kind,
and `rows=` decodes only the top rows a crop needs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from morphgs import media


@pytest.mark.parametrize("mode", ["RGB", "RGBA", "L", "LA", "P", "I;16", "1"])
def test_native_png_frames_match_pillow(tmp_path: Path, mode: str) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (3, 9, 7, 3), dtype=np.uint8)
    folder = tmp_path / mode.replace(";", "")
    folder.mkdir()
    for i, frame in enumerate(rgb):
        im = Image.fromarray(frame)
        if mode == "RGBA":
            im = im.convert("RGBA")
        elif mode == "I;16":
            im = Image.frombytes("I;16", (7, 9), (frame[..., 0].astype("<u2") * 257).tobytes())
        else:
            im = im.convert(mode)
        im.save(folder / f"{i:05d}.png")
    expected = np.stack([np.asarray(Image.open(f).convert("RGB")) for f in sorted(folder.iterdir())])
    if mode == "I;16":  # Pillow clips 16-bit gray to 255 on convert; the native path keeps the high byte
        expected = np.repeat(rgb[..., :1], 3, axis=-1)
    np.testing.assert_array_equal(media.read_clip(folder), expected)


def test_rows_decodes_only_the_top_of_every_frame(tmp_path: Path) -> None:
    rgb = np.random.default_rng(1).integers(0, 256, (4, 20, 6, 3), dtype=np.uint8)
    media.write_frames(tmp_path / "png", rgb)
    np.testing.assert_array_equal(media.read_clip(tmp_path / "png", start=1, count=2, rows=5), rgb[1:3, :5])
    np.testing.assert_array_equal(media.read_clip(tmp_path / "png", rows=99), rgb)  # more rows than there are
    (tmp_path / "jpg").mkdir()
    for i, f in enumerate(rgb):
        Image.fromarray(f).save(tmp_path / "jpg" / f"{i:05d}.jpg", quality=95)
    assert media.read_clip(tmp_path / "jpg", rows=5).shape == (4, 5, 6, 3)
    with pytest.raises(ValueError, match="rows >= 1"):
        media.read_clip(tmp_path / "png", rows=0)


def test_a_frame_of_another_size_is_named_even_when_only_top_rows_are_read(tmp_path: Path) -> None:
    rgb = np.zeros((3, 10, 8, 3), np.uint8)
    media.write_frames(tmp_path, rgb)
    Image.new("RGB", (8, 12)).save(tmp_path / "00002.png")  # taller
    with pytest.raises(media.MediaError, match="00002.png: frame of 8x12, but 00000.png is 8x10"):
        media.read_clip(tmp_path, rows=4)
