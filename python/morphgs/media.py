"""Frames and videos on disk: one place that reads and writes what curation, training, refinement,
evaluation and the exports exchange.

A *clip* is a folder of numbered frames (PNG or JPEG, sorted by name, e.g. `00000.png`) or a video
file (MP4 and whatever else ffmpeg decodes), read as uint8 RGB (F, H, W, 3). Depth maps are
single-channel float32 OpenEXR files (`00000.depth.exr`, as `morphgs curate --depth` writes them),
read as (F, H, W).

PNG frames are decoded natively (Rust `png` crate, in parallel; `rows=` stops each frame after its
top rows, which is all a crop needs); JPEGs need Pillow and videos imageio-ffmpeg
(`pip install 'morphgs[video]'`), both imported only when used. Every problem is a `MediaError` (a `MorphgsError`, so a `ValueError`)
that names the file: an empty folder, an unreadable image, frames of different sizes, a video
ffmpeg cannot decode. A missing path is a `FileNotFoundError`.
"""

from __future__ import annotations

import os
import re
import subprocess
import threading
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from morphgs._core import MorphgsError

__all__ = [
    "IMAGE_SUFFIXES",
    "VIDEO_SUFFIXES",
    "MediaError",
    "clip_info",
    "encode_frames",
    "frame_paths",
    "is_video",
    "read_clip",
    "read_depth",
    "write_frames",
    "write_video",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".webm", ".avi")
# a refusal limit for images and videos whose header claims more pixels than any real clip has
_MAX_VALUES = 1 << 31


class MediaError(MorphgsError):
    """A frame folder, image or video that cannot be read as a clip (names the file)."""


def is_video(path: str | os.PathLike[str]) -> bool:
    """Whether `path` names a video file (by its suffix)."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def frame_paths(folder: str | os.PathLike[str], suffixes: Sequence[str] = IMAGE_SUFFIXES) -> list[Path]:
    """The frame files of a folder, sorted by name. Depth EXRs and hidden files are not frames."""
    d = Path(folder)
    if not d.exists():
        raise FileNotFoundError(f"{d}: no such folder")
    if not d.is_dir():
        raise MediaError(f"{d}: not a folder of frames")
    files = sorted(p for p in d.iterdir()
                   if p.suffix.lower() in suffixes and not p.name.startswith(".") and p.is_file())
    if not files:
        raise MediaError(f"{d}: no frames ({', '.join(suffixes)} files) in this folder")
    return files


def _ffmpeg() -> str:
    try:
        import imageio_ffmpeg
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise MediaError("reading or writing videos needs imageio-ffmpeg: pip install 'morphgs[video]'") from e
    return str(imageio_ffmpeg.get_ffmpeg_exe())


def _video_size(path: Path) -> tuple[int, int, int]:
    """(width, height, frame count) of a video's first video stream: ffmpeg copies the stream
    to nowhere (no decoding) and reports the size and the frames it passed."""
    proc = subprocess.run([_ffmpeg(), "-hide_banner", "-nostats", "-v", "info", "-i", str(path), "-map", "0:v:0",
                           "-c", "copy", "-f", "null", "-"], capture_output=True, check=False)
    err = proc.stderr.decode(errors="replace")
    size = re.search(r"Stream #\S+.*Video: .*?, (\d+)x(\d+)", err)
    frames = re.findall(r"frame=\s*(\d+)", err)
    if proc.returncode != 0 or size is None or not frames:
        last = err.strip().splitlines()[-1] if err.strip() else "no output"
        raise MediaError(f"{path}: not a readable video ({last})")
    return int(size.group(1)), int(size.group(2)), int(frames[-1])


def clip_info(path: str | os.PathLike[str]) -> tuple[int, int, int]:
    """(frames, height, width) of a clip without decoding all of it."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder")
    if p.is_file():
        if not is_video(p):
            raise MediaError(f"{p}: not a video ({', '.join(VIDEO_SUFFIXES)}) or a folder of frames")
        _ffmpeg()
        w, h, n = _video_size(p)
        return n, h, w
    files = frame_paths(p)
    h, w = _image_size(files[0])
    return len(files), h, w


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise MediaError(f"{path}: not a readable image ({e})") from None
    return h, w


def read_image(path: Path) -> np.ndarray:
    """One image file as (H, W, 3) uint8 RGB (grey and RGBA converted).

    Raises:
        MediaError: the file cannot be read as an image (names it).
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.width * im.height * 3 > _MAX_VALUES:
                raise MediaError(f"{path}: image of {im.width}x{im.height} is too large")
            return np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        if isinstance(e, MediaError):
            raise
        raise MediaError(f"{path}: not a readable image ({e})") from None


def read_clip(
    path: str | os.PathLike[str],
    *,
    start: int = 0,
    count: int | None = None,
    rows: int | None = None,
) -> np.ndarray:
    """Frames `start .. start+count` of a clip as uint8 RGB (F, H, W, 3).

    PNG frames are decoded natively, in parallel (3x faster than Pillow on one core); JPEGs go
    through Pillow, videos through ffmpeg.

    Args:
        path: a folder of frames or a video file.
        start, count: a window of frames (all frames from `start` when count is None).
        rows: only the top `rows` rows of every frame (e.g. what a crop needs): PNG rows below
            them are not even decompressed; other formats are decoded whole and cut.

    Raises:
        FileNotFoundError: no such path. MediaError: an empty folder, an unreadable image or video,
        frames of different sizes, or a window past the clip's end (names the file).
    """
    p = Path(path)
    if start < 0 or (count is not None and count < 0) or (rows is not None and rows < 1):
        raise ValueError(f"start and count must be >= 0 and rows >= 1, got {start}, {count}, {rows}")
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder")
    if p.is_file():
        clip = _read_video(p, start, count)
        return clip if rows is None else np.ascontiguousarray(clip[:, :rows])
    files = frame_paths(p)
    stop = len(files) if count is None else start + count
    if stop > len(files):
        raise MediaError(f"{p}: frames {start}..{stop - 1} asked for, the clip has {len(files)}")
    window = files[start:stop]
    if not window:
        return np.zeros((0, 0, 0, 3), np.uint8)
    frames, sizes = _read_images(window, rows)
    for name, size in zip(window, sizes):
        if size != sizes[0]:
            raise MediaError(f"{name}: frame of {size[1]}x{size[0]}, but {window[0].name} is "
                             f"{sizes[0][1]}x{sizes[0][0]}: frames of one clip must share a size")
    return np.stack(frames)


def _read_images(files: Sequence[Path], rows: int | None) -> tuple[list[np.ndarray], list[tuple[int, int]]]:
    """Decode frames (the top `rows` rows when given): (arrays, full (H, W) of each file)."""
    from morphgs import _core

    frames: list[np.ndarray | None] = [None] * len(files)
    sizes: list[tuple[int, int]] = [(0, 0)] * len(files)
    png = [i for i, f in enumerate(files) if f.suffix.lower() == ".png"]
    if png:
        try:
            decoded = _core._read_png_batch([files[i] for i in png], rows, _MAX_VALUES)
        except (MorphgsError, OSError) as e:
            raise MediaError(str(e)) from None
        for i, (arr, height) in zip(png, decoded):
            frames[i], sizes[i] = arr, (int(height), arr.shape[1])
    for i, f in enumerate(files):
        if frames[i] is None:
            img = read_image(f)
            sizes[i] = img.shape[:2]
            frames[i] = img if rows is None else img[:rows]
    return [f for f in frames if f is not None], sizes


def _check_same_size(frames: Sequence[np.ndarray], files: Sequence[Path]) -> None:
    for f, name in zip(frames, files):
        if f.shape != frames[0].shape:
            raise MediaError(f"{name}: frame of {f.shape[1]}x{f.shape[0]}, but {files[0].name} is "
                             f"{frames[0].shape[1]}x{frames[0].shape[0]}: frames of one clip must share a size")


def _read_video(p: Path, start: int, count: int | None) -> np.ndarray:
    if not is_video(p):
        raise MediaError(f"{p}: not a video ({', '.join(VIDEO_SUFFIXES)}) or a folder of frames")
    exe = _ffmpeg()
    w, h, n = _video_size(p)
    if w * h * 3 * max(n, 1) > _MAX_VALUES:
        raise MediaError(f"{p}: video of {n} frames at {w}x{h} is too large to read at once; pass count=")
    stop = n if count is None else start + count
    if stop > n:
        raise MediaError(f"{p}: frames {start}..{stop - 1} asked for, the video has {n}")
    # select frames by index in the decoder so a window costs only its own frames' conversion
    vf = f"select='between(n\\,{start}\\,{stop - 1})'"
    cmd = [exe, "-v", "error", "-i", str(p), "-vf", vf, "-fps_mode", "passthrough", "-f", "rawvideo", "-pix_fmt", "rgb24", "-"]
    proc = subprocess.run(cmd, capture_output=True, check=False)
    if proc.returncode != 0:
        raise MediaError(f"{p}: ffmpeg could not decode it: {proc.stderr.decode(errors='replace').strip()}")
    raw = np.frombuffer(proc.stdout, np.uint8)
    if raw.size != (stop - start) * h * w * 3:
        raise MediaError(f"{p}: decoded {raw.size // max(h * w * 3, 1)} frames, expected {stop - start}")
    return raw.reshape(stop - start, h, w, 3).copy()


def read_depth(paths: Sequence[str | os.PathLike[str]] | str | os.PathLike[str]) -> np.ndarray:
    """Single-channel float32 EXR depth maps as (F, H, W): a list of files, or a folder whose
    `*.depth.exr` files (as `morphgs curate --depth` and `Render.save` write them beside
    `*.alpha.exr` maps) are read in name order — or all its `*.exr` files when none is named
    `.depth.exr`. Files are decoded in parallel (Rust)."""
    from morphgs import _core

    if isinstance(paths, (str, os.PathLike)):
        files = frame_paths(paths, suffixes=(".exr",))
        named = [f for f in files if f.name.lower().endswith(".depth.exr")]
        files = named or files
    else:
        files = [Path(p) for p in paths]
    for f in files:
        if not f.is_file():
            raise FileNotFoundError(f"{f}: no such depth file")
    if not files:
        raise MediaError("no depth files given")
    maps = _core._read_exr_batch(files)
    out = []
    for f, m in zip(files, maps):
        if m.ndim != 2:
            raise MediaError(f"{f}: a depth map has one channel, this EXR has {m.shape[2]}")
        out.append(m)
    _check_same_size(out, files)
    return np.stack(out)


def _as_uint8(frames: np.ndarray | Iterable[np.ndarray]) -> np.ndarray:
    arr = np.asarray(frames if isinstance(frames, np.ndarray) else list(frames))
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise ValueError(f"frames must be (F, H, W, 3), got shape {arr.shape}")
    if arr.dtype != np.uint8:
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"frames must be uint8 or float in [0, 1], got {arr.dtype}")
        arr = np.rint(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.ascontiguousarray(arr)


def write_frames(folder: str | os.PathLike[str], frames: np.ndarray | Iterable[np.ndarray], *,
                 start: int = 0) -> list[Path]:
    """Write frames (uint8, or float in [0, 1]) as `{i:05d}.png` files (atomically, in parallel)."""
    from morphgs import _core

    arr = _as_uint8(frames)
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    paths = [d / f"{start + i:05d}.png" for i in range(len(arr))]
    if len(arr):
        _core._write_png_batch(paths, arr)
    return paths


def _x264_output(*, fps: float, crf: int) -> list[str]:
    """ffmpeg output options shared by every MP4 morphgs writes: H.264 in yuv420p (every player and
    trainer decodes it) with the BT.601 matrix that untagged-video readers (decord, ffmpeg's own
    rgb24 output) assume, tagged as such; odd sides padded by one pixel; one encoder thread and
    bit-exact muxing, so the same frames give the same bytes on every run."""
    return ["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-r", str(fps), "-c:v", "libx264", "-pix_fmt", "yuv420p",
            "-crf", str(crf), "-preset", "medium", "-threads", "1", "-colorspace", "smpte170m",
            "-color_primaries", "smpte170m", "-color_trc", "smpte170m", "-color_range", "tv",
            "-flags:v", "+bitexact", "-fflags", "+bitexact", "-map_metadata", "-1", "-movflags", "+faststart"]


def _run_ffmpeg(cmd: list[str], out: Path, tmp: Path, stdin: bytes | None = None) -> Path:
    proc = subprocess.run(cmd, input=stdin, capture_output=True, check=False)
    if proc.returncode != 0:
        tmp.unlink(missing_ok=True)
        raise MediaError(f"{out}: ffmpeg failed: {proc.stderr.decode(errors='replace').strip()}")
    os.replace(tmp, out)
    return out


def _tmp_beside(out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    return out.with_name(f".{out.name}.tmp{os.getpid()}-{threading.get_ident()}{out.suffix}")


def write_video(path: str | os.PathLike[str], frames: np.ndarray | Iterable[np.ndarray], *, fps: float = 16,
                crf: int = 18) -> Path:
    """Encode frames (uint8, or float in [0, 1]) as an H.264 MP4 (yuv420p, so every player opens it;
    odd sizes are padded by one pixel). Written to a temporary beside `path`, then renamed."""
    arr = _as_uint8(frames)
    if len(arr) == 0:
        raise ValueError(f"{path}: no frames to encode")
    exe = _ffmpeg()
    out = Path(path)
    tmp = _tmp_beside(out)
    _, h, w, _ = arr.shape
    cmd = [exe, "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}", "-r", str(fps),
           "-i", "-", *_x264_output(fps=fps, crf=crf), str(tmp)]
    return _run_ffmpeg(cmd, out, tmp, stdin=arr.tobytes())


_NUMBERED = re.compile(r"^(\d{5})\.png$")


def encode_frames(folder: str | os.PathLike[str], path: str | os.PathLike[str], *, fps: float = 16,
                  crf: int = 18) -> Path:
    """Encode a folder of frames as an H.264 MP4, as `write_video(path, read_clip(folder))` would.

    Frames numbered `00000.png, 00001.png, ...` (what `morphgs curate` writes) are read by ffmpeg
    itself, with no decoding in Python, so several folders can be encoded at once from threads; any
    other folder of frames is read with `read_clip` first. Written to a temporary, then renamed.

    Raises:
        FileNotFoundError: no such folder. MediaError: no frames, or ffmpeg failed (names the file).
    """
    files = frame_paths(folder)
    numbered = all((m := _NUMBERED.match(f.name)) is not None and int(m.group(1)) == i for i, f in enumerate(files))
    if not numbered:
        return write_video(path, read_clip(folder), fps=fps, crf=crf)
    exe = _ffmpeg()
    out = Path(path)
    tmp = _tmp_beside(out)
    cmd = [exe, "-v", "error", "-y", "-f", "image2", "-framerate", str(fps), "-start_number", "0",
           "-i", str(Path(folder) / "%05d.png"), "-frames:v", str(len(files)),
           *_x264_output(fps=fps, crf=crf), str(tmp)]
    return _run_ffmpeg(cmd, out, tmp)
