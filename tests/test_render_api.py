"""The render API: shapes, options, edge cases, image files, determinism and fork safety."""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs._core import _write_exr, _write_png

REPO = Path(__file__).resolve().parents[1]


def scene_of(n: int = 300, degree: int = 1, seed: int = 0) -> morphgs.GaussianScene:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return morphgs.GaussianScene.from_arrays(
        means=rng.uniform(-1, 1, (n, 3)), quats=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(-4, -2, (n, 3)), opacity_logits=rng.normal(1, 1, n),
        sh0=rng.normal(0, 0.5, (n, 3)), sh_rest=rng.normal(0, 0.2, (n, k, 3)) if k else None,
    )


def camera(width: int = 64, height: int = 48) -> morphgs.Camera:
    return morphgs.Camera.look_at([0.3, -0.2, -4.0], [0, 0, 0], up=[0, -1, 0],
                                  fov_y_degrees=40, width=width, height=height)


def test_single_camera_gives_hw_images_and_cameras_give_frames() -> None:
    scene = scene_of()
    r = morphgs.render(scene, camera())
    assert r.rgb.shape == (48, 64, 3) and r.depth.shape == (48, 64) and r.alpha.shape == (48, 64)
    assert r.rgb.dtype == np.float32 and not r.batched and len(r) == 1
    cams = morphgs.Cameras.from_list([camera(), camera().resized(64, 48)])
    rb = morphgs.render(scene, cams)
    assert rb.rgb.shape == (2, 48, 64, 3) and len(rb) == 2 and rb.batched
    np.testing.assert_array_equal(rb[0].rgb, r.rgb)
    np.testing.assert_array_equal(rb[-1].alpha, rb.alpha[1])
    assert [f.rgb.shape for f in rb] == [(48, 64, 3)] * 2
    with pytest.raises(IndexError):
        rb[2]
    assert r.stats["frames"] == 1 and r.stats["evaluations"] > 0 and r.stats["visible"] > 0
    assert {"project_s", "sort_s", "bin_s", "blend_s", "simd", "threads"} <= set(r.stats)


def test_morphgs_simd_picks_the_blend_kernel_and_the_fast_kernels_agree_bit_for_bit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a dense scene (early termination) at a size with partial tiles
    scene, cam = scene_of(n=4000, degree=2), camera(83, 61)
    results = {}
    for level in ["scalar", "avx2", "avx512", "auto"]:
        monkeypatch.setenv("MORPHGS_SIMD", level)
        results[level] = r = morphgs.render(scene, cam)
        assert r.stats["evaluations"] > 0
    best = results["auto"].stats["simd"]
    assert results["scalar"].stats["simd"] == "scalar"
    # a level the CPU lacks falls back to the best one below it
    assert results["avx512"].stats["simd"] == best
    for level in ["avx2", "avx512"]:
        if results[level].stats["simd"] == "scalar":
            continue
        # the explicit AVX2 and AVX-512 kernels give the same bits (they blend different work
        # units, 8x1 and 4x4 pixels, so their evaluation counts differ; the Rust tests hold
        # each count to a model of its unit)
        for field in ("rgb", "depth", "alpha"):
            np.testing.assert_array_equal(getattr(results[level], field),
                                          getattr(results["auto"], field))
        # the explicit kernels skip the lanes of a 16-pixel row a footprint misses
        assert results[level].stats["evaluations"] <= results["scalar"].stats["evaluations"]
    # the plain kernel rounds without FMA: last-bit differences only
    np.testing.assert_allclose(results["scalar"].rgb, results["auto"].rgb, atol=1e-5)
    monkeypatch.setenv("MORPHGS_SIMD", "sse9")
    with pytest.raises(ValueError, match="MORPHGS_SIMD"):
        morphgs.render(scene, cam)


def test_render_many_equals_separate_renders() -> None:
    a, b = scene_of(seed=1), scene_of(seed=2, degree=0)
    cams = [camera(), camera(64, 48)]
    both = morphgs.render_many([a, b], cams)
    for scene, got in zip([a, b], both):
        np.testing.assert_array_equal(got.rgb, morphgs.render(scene, cams).rgb)


def test_to_uint8_rounds_clipped_colour() -> None:
    r = morphgs.Render(rgb=np.array([[[-0.5, 0.5, 1.5]]], np.float32),
                       depth=np.zeros((1, 1), np.float32), alpha=np.zeros((1, 1), np.float32))
    assert r.to_uint8().tolist() == [[[0, 128, 255]]]


def test_empty_scene_renders_the_background() -> None:
    empty = scene_of(0)
    r = morphgs.render(empty, camera(), background=(0.25, 0.5, 1.0))
    assert np.all(r.rgb == np.array([0.25, 0.5, 1.0], np.float32))
    assert np.all(r.alpha == 0) and np.all(r.depth == 0)


def test_background_shows_through_by_transmittance() -> None:
    scene = scene_of()
    black = morphgs.render(scene, camera())
    white = morphgs.render(scene, camera(), background=(1, 1, 1))
    np.testing.assert_allclose(white.rgb - black.rgb, np.repeat(1 - black.alpha[..., None], 3, -1),
                               atol=1e-6)


def test_zero_size_and_non_finite_cameras_raise_value_error() -> None:
    scene = scene_of()
    with pytest.raises(ValueError):
        camera(0, 48)
    w2c = np.eye(4)
    w2c[0, 3] = np.nan
    with pytest.raises(ValueError):
        morphgs.Camera(100, 100, 32, 24, 64, 48, w2c)
    with pytest.raises(ValueError):
        morphgs.Cameras(world_to_camera=w2c[None], K=np.eye(3)[None], width=64, height=48)
    # the native entry point checks too (callers that bypass the Camera classes)
    from morphgs._core import _render
    k = np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])[None]
    with pytest.raises(ValueError, match="NaN or Inf"):
        _render([scene], w2c[None], k, 64, 48)
    with pytest.raises(ValueError, match="positive"):
        _render([scene], np.eye(4)[None], k, 0, 48)


def test_bad_options_raise_value_error() -> None:
    scene = scene_of(degree=1)
    with pytest.raises(ValueError, match="exceeds"):
        morphgs.render(scene, camera(), sh_degree=2)
    with pytest.raises(ValueError):
        morphgs.render(scene, camera(), max_alpha=0.0)
    with pytest.raises(ValueError):
        morphgs.render(scene, camera(), background=(0, np.nan, 0))
    with pytest.raises(TypeError):
        morphgs.render(scene, "front")  # type: ignore[arg-type]


def test_lower_sh_degree_changes_view_dependent_colour_only() -> None:
    scene = scene_of(degree=2)
    full = morphgs.render(scene, camera())
    dc = morphgs.render(scene, camera(), sh_degree=0)
    np.testing.assert_array_equal(full.alpha, dc.alpha)
    assert np.abs(full.rgb - dc.rgb).max() > 1e-3


def test_non_finite_gaussians_are_skipped_never_nan() -> None:
    base = scene_of(200, degree=0)
    means = np.array(base.means)
    logits = np.array(base.opacity_logits)
    scales = np.array(base.log_scales)
    means[3] = [np.nan, 0, 0]
    logits[5] = np.inf
    scales[7] = [np.inf, 0, 0]
    sh0 = np.array(base.sh0)
    sh0[9] = [np.nan, 0, 0]
    sh0[11] = [-np.inf, 0, 0]
    scales[13] = [-np.inf, 0, 0]
    bad = morphgs.GaussianScene.from_arrays(means=means, quats=base.quats, log_scales=scales,
                                            opacity_logits=logits, sh0=sh0)
    r = morphgs.render(bad, camera())
    assert np.all(np.isfinite(r.rgb)) and np.all(np.isfinite(r.depth)) and np.all(np.isfinite(r.alpha))
    keep = np.setdiff1d(np.arange(200), [3, 5, 7, 9, 11, 13])
    clean_scene = morphgs.GaussianScene.from_arrays(
        means=means[keep], quats=np.array(base.quats)[keep], log_scales=scales[keep],
        opacity_logits=logits[keep], sh0=sh0[keep])
    clean = morphgs.render(clean_scene, camera())
    np.testing.assert_array_equal(r.rgb, clean.rgb)


def test_save_writes_png_and_float_exr_per_frame(tmp_path: Path) -> None:
    from PIL import Image

    scene = scene_of()
    r = morphgs.render(scene, morphgs.Cameras.from_list([camera(), camera()]))
    paths = r.save(tmp_path / "out")
    assert [p.name for p in paths] == ["00000.png", "00001.png"]
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == ["00000.alpha.exr", "00000.depth.exr", "00000.png",
                     "00001.alpha.exr", "00001.depth.exr", "00001.png"]
    png = np.asarray(Image.open(paths[1]))
    np.testing.assert_array_equal(png, r.to_uint8()[1])
    # OpenEXR magic, one float channel "Y" (values are checked against the exr decoder in the
    # Rust tests of image_out)
    head = (tmp_path / "out" / "00000.depth.exr").read_bytes()
    assert head[:4] == b"\x76\x2f\x31\x01"
    assert b"channels\x00chlist\x00" in head and b"Y\x00\x02\x00\x00\x00" in head


def test_writers_reject_wrong_dtypes_and_shapes(tmp_path: Path) -> None:
    with pytest.raises(TypeError):
        _write_png(tmp_path / "a.png", np.zeros((4, 4, 3), np.float64))  # uint8 or float32 colour only
    with pytest.raises(ValueError):
        _write_png(tmp_path / "a.png", np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(ValueError):
        _write_exr(tmp_path / "a.exr", np.zeros((4,), np.float32))
    with pytest.raises(FileNotFoundError):
        _write_exr(tmp_path / "missing" / "a.exr", np.zeros((4, 4), np.float32))
    assert not any(tmp_path.iterdir())


_DETERMINISM = textwrap.dedent(
    """
    import hashlib, numpy as np, morphgs, sys
    sys.path.insert(0, {tests!r})
    from render_reference import garden
    from pathlib import Path
    scene, cams = garden(Path({fixtures!r}))
    r = morphgs.render(scene, cams.resized(200, 130), max_alpha=0.999)
    h = hashlib.sha256()
    for a in (r.rgb, r.depth, r.alpha):
        h.update(a.tobytes())
    print(morphgs.num_threads(), h.hexdigest())
    """
)


def test_output_bytes_do_not_depend_on_thread_count(fixtures_dir: Path) -> None:
    code = _DETERMINISM.format(tests=str(REPO / "tests"), fixtures=str(fixtures_dir))
    digests = {}
    for n in ("1", "2", "8"):
        env = dict(os.environ, RAYON_NUM_THREADS=n)
        env.pop("MORPHGS_NUM_THREADS", None)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, timeout=300, check=True).stdout.split()
        assert out[0] == n
        digests[n] = out[1]
    assert len(set(digests.values())) == 1, digests


def _render_digest(queue: multiprocessing.Queue) -> None:  # type: ignore[type-arg]
    r = morphgs.render(scene_of(), camera())
    queue.put(hashlib.sha256(r.rgb.tobytes()).hexdigest())


def test_render_after_fork_finishes_in_the_child() -> None:
    parent = hashlib.sha256(morphgs.render(scene_of(), camera()).rgb.tobytes()).hexdigest()
    # os.fork: the child renders and reports through a pipe
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        try:
            r = morphgs.render(scene_of(), camera())
            os.write(wfd, hashlib.sha256(r.rgb.tobytes()).hexdigest().encode())
        finally:
            os._exit(0)
    os.close(wfd)
    import select
    ready, _, _ = select.select([rfd], [], [], 60)
    if not ready:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
        pytest.fail("render in an os.fork child did not finish within 60 s")
    child = os.read(rfd, 128).decode()
    os.close(rfd)
    os.waitpid(pid, 0)
    assert child == parent
    # multiprocessing's 'fork' context, as torch DataLoader workers use
    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_render_digest, args=(q,))
    p.start()
    p.join(60)
    if p.is_alive():
        p.kill()
        pytest.fail("render in a multiprocessing 'fork' child did not finish within 60 s")
    assert q.get(timeout=5) == parent
