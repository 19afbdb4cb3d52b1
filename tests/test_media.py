"""morphgs.media: clips (frame folders and MP4s) and EXR depth maps, read back as written, and
every bad input a clear MediaError naming the file."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from morphgs import MorphgsError, media


def _frames(n: int = 5, h: int = 24, w: int = 32, seed: int = 0) -> np.ndarray:
    # smooth content so H.264 keeps it close
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x / w, y / h, 0.5 + 0 * x], -1)
    return np.stack([np.clip(base + 0.1 * i / n + 0.01 * seed, 0, 1) for i in range(n)])


def test_png_folder_round_trip_is_exact_and_windows_select_frames(tmp_path: Path) -> None:
    f = _frames()
    u8 = np.rint(f * 255).astype(np.uint8)
    paths = media.write_frames(tmp_path / "clip", f)
    assert [p.name for p in paths] == [f"{i:05d}.png" for i in range(5)]
    np.testing.assert_array_equal(media.read_clip(tmp_path / "clip"), u8)
    np.testing.assert_array_equal(media.read_clip(tmp_path / "clip", start=1, count=3), u8[1:4])
    assert media.clip_info(tmp_path / "clip") == (5, 24, 32)


def test_mp4_round_trip_keeps_count_size_and_content(tmp_path: Path) -> None:
    u8 = np.rint(_frames(n=9, h=48, w=64) * 255).astype(np.uint8)
    out = media.write_video(tmp_path / "v.mp4", u8, fps=8)
    assert media.clip_info(out) == (9, 48, 64)
    back = media.read_clip(out)
    assert back.shape == u8.shape
    assert np.abs(back.astype(int) - u8).mean() < 3.0  # lossy, but close
    window = media.read_clip(out, start=4, count=3)
    np.testing.assert_array_equal(window, back[4:7])
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary was renamed into place


def test_encode_frames_gives_the_bytes_write_video_gives_and_the_same_bytes_every_time(tmp_path: Path) -> None:
    u8 = np.rint(_frames(n=5, h=48, w=64) * 255).astype(np.uint8)
    media.write_frames(tmp_path / "clip", u8)
    a = media.encode_frames(tmp_path / "clip", tmp_path / "a.mp4", fps=8)
    b = media.encode_frames(tmp_path / "clip", tmp_path / "b.mp4", fps=8)
    c = media.write_video(tmp_path / "c.mp4", u8, fps=8)
    assert a.read_bytes() == b.read_bytes() == c.read_bytes()
    # frames not numbered 00000.png... go through read_clip, with the same result
    (tmp_path / "named").mkdir()
    for i, f in enumerate(sorted((tmp_path / "clip").iterdir())):
        (tmp_path / "named" / f"frame_{i + 10}.png").write_bytes(f.read_bytes())
    d = media.encode_frames(tmp_path / "named", tmp_path / "d.mp4", fps=8)
    assert d.read_bytes() == a.read_bytes()
    with pytest.raises(FileNotFoundError):
        media.encode_frames(tmp_path / "nothing", tmp_path / "e.mp4")


def test_mp4_keeps_saturated_colours_and_says_which_matrix_it_used(tmp_path: Path) -> None:
    """Flat saturated colours come back within limited-range rounding, and the stream is tagged
    BT.601 (smpte170m, tv range): the matrix it was converted with, which is also what decoders
    that ignore tags (decord's swscale default) assume, so every reader sees the same colours."""
    colours = [(200, 50, 100), (30, 180, 60), (40, 60, 220), (240, 220, 30), (128, 128, 128)]
    u8 = np.stack([np.broadcast_to(np.array(c, np.uint8), (32, 48, 3)) for c in colours])
    out = media.write_video(tmp_path / "v.mp4", u8, crf=0)
    back = media.read_clip(out).astype(int)
    assert np.abs(back.mean(axis=(1, 2)) - np.array(colours)).max() <= 3
    info = subprocess.run([media._ffmpeg(), "-hide_banner", "-i", str(out)], capture_output=True, text=True).stderr
    assert "yuv420p(tv, smpte170m" in info


def test_depth_exr_folder_reads_back_bit_exact(tmp_path: Path) -> None:
    from morphgs import _core

    d = np.random.default_rng(1).random((3, 7, 5)).astype(np.float32) * 10
    (tmp_path / "depth").mkdir()
    _core._write_exr_batch([tmp_path / "depth" / f"{i:05d}.depth.exr" for i in range(3)], d)
    np.testing.assert_array_equal(media.read_depth(tmp_path / "depth"), d)


@pytest.mark.parametrize("case", ["empty", "unreadable", "sizes", "past_end", "not_video", "bad_video", "rgb_depth"])
def test_bad_clips_raise_media_errors_naming_the_file(tmp_path: Path, case: str) -> None:
    clip = tmp_path / "clip"
    clip.mkdir()
    target: Path = clip
    kwargs: dict = {}
    if case == "unreadable":
        media.write_frames(clip, _frames(n=2))
        (clip / "00002.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        target, name = clip, "00002.png"
    elif case == "sizes":
        media.write_frames(clip, _frames(n=2))
        media.write_frames(clip, _frames(n=1, h=12), start=2)
        name = "00002.png"
    elif case == "past_end":
        media.write_frames(clip, _frames(n=2))
        kwargs, name = {"start": 1, "count": 4}, "clip"
    elif case == "not_video":
        target = tmp_path / "notes.txt"
        target.write_text("hello")
        name = "notes.txt"
    elif case == "bad_video":
        target = tmp_path / "broken.mp4"
        target.write_bytes(b"\x00\x00\x00\x18ftypmp42 truncated")
        name = "broken.mp4"
    elif case == "rgb_depth":
        from morphgs import _core

        _core._write_exr(tmp_path / "rgb.exr", np.zeros((4, 4, 3), np.float32))
        with pytest.raises(MorphgsError, match="rgb.exr.*one channel"):
            media.read_depth([tmp_path / "rgb.exr"])
        return
    else:
        name = "clip"
    with pytest.raises(media.MediaError, match=name):
        media.read_clip(target, **kwargs)
    assert issubclass(media.MediaError, MorphgsError) and issubclass(media.MediaError, ValueError)


def test_missing_paths_are_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope"):
        media.read_clip(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="gone.exr"):
        media.read_depth([tmp_path / "gone.exr"])
