"""Rendering into reusable output memory (`render_many(..., out=RenderBuffers(...))`) and curation's
double-buffered chunks: the same values as fresh arrays, whatever the memory held before."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import _core, synthetic, trajectory
from morphgs.rendering import RenderBuffers


def _scene_and_path(frames: int, size: tuple[int, int] = (56, 40)) -> tuple[morphgs.GaussianScene, morphgs.Cameras]:
    scene = synthetic.scene(n_gaussians=2000, sh_degree=1, seed=5)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], frames, fov_y_degrees=50.0,
                            resolution=size)
    return scene, cams


def _bits(r: morphgs.Render) -> tuple[bytes, bytes, bytes]:
    return r.rgb.tobytes(), r.depth.tobytes(), r.alpha.tobytes()


def test_renders_into_buffers_hold_the_values_of_fresh_arrays_whatever_was_there() -> None:
    scene, cams = _scene_and_path(6)
    other = morphgs.perturb(scene, "morphological", seed=3)
    buffers = RenderBuffers(sets=2)
    # batches of different sizes: the buffers grow, then smaller batches use a prefix
    for frames in (cams[:3], cams, cams[2:3], cams[1:5]):
        want = morphgs.render_many([scene, other], frames)
        got = morphgs.render_many([scene, other], frames, out=buffers)
        assert [_bits(r) for r in got] == [_bits(r) for r in want]
        assert got[0].rgb.shape == want[0].rgb.shape and got[0].rgb.dtype == np.float32
        for r in got:  # poison the memory: the next render into this set must overwrite it all
            for a in (r.rgb, r.depth, r.alpha):
                a.fill(np.nan)
    single = morphgs.render_many([scene], cams[0], out=buffers)[0]  # one Camera: (H,W) images
    assert _bits(single) == _bits(morphgs.render(scene, cams[0]))


def test_a_render_stays_valid_until_its_set_comes_round_again() -> None:
    scene, cams = _scene_and_path(3)
    want = [_bits(morphgs.render(scene, cams[i])) for i in range(3)]
    two = RenderBuffers(sets=2)
    a = morphgs.render_many([scene], cams[0], out=two)[0]
    b = morphgs.render_many([scene], cams[1], out=two)[0]
    assert (_bits(a), _bits(b)) == (want[0], want[1])  # double buffered: both intact
    c = morphgs.render_many([scene], cams[2], out=two)[0]
    assert _bits(a) == _bits(c) == want[2]  # the first set was reused
    one = RenderBuffers()
    d = morphgs.render_many([scene], cams[0], out=one)[0]
    morphgs.render_many([scene], cams[1], out=one)
    assert _bits(d) == want[1]


def test_bad_buffers_are_refused() -> None:
    scene, cams = _scene_and_path(2)
    with pytest.raises(TypeError, match="RenderBuffers"):
        morphgs.render_many([scene], cams, out=(np.zeros(3),))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sets"):
        RenderBuffers(sets=0)
    w2c = np.ascontiguousarray(cams.world_to_camera)
    k = np.ascontiguousarray(cams.K)
    shape = (1, 2, cams.height, cams.width)
    ok = (np.empty((*shape, 3), np.float32), np.empty(shape, np.float32), np.empty(shape, np.float32))
    rgb, _, _, _ = _core._render([scene], w2c, k, cams.width, cams.height, out=ok)
    assert rgb is ok[0]
    cases = {
        "shape": (ok[0][:, :1], ok[1], ok[2]),
        "C-contiguous": (ok[0], np.asfortranarray(ok[1]), ok[2]),
        "cannot be written": (ok[0], ok[1], ok[1]),  # the same array twice
    }
    for what, out in cases.items():
        with pytest.raises(ValueError, match=what):
            _core._render([scene], w2c, k, cams.width, cams.height, out=out)
    with pytest.raises(TypeError, match="float32"):
        _core._render([scene], w2c, k, cams.width, cams.height, out=(ok[0], ok[1].astype(np.float64), ok[2]))


def test_curated_chunks_hold_the_pair_rendered_in_one_call(tmp_path: Path) -> None:
    """Chunks of 2 of 5 frames go through two alternating buffer sets while a writer thread writes the
    previous chunk: every PNG and depth map is the whole path's render."""
    scene, cams = _scene_and_path(5)
    folder = tmp_path / "scene"
    folder.mkdir()
    morphgs.save_ply(scene, folder / "scene.ply")
    gl = cams.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])
    (folder / "camera_path.json").write_text(json.dumps({
        "camera_type": "perspective", "render_width": cams.width, "render_height": cams.height,
        "camera_path": [{"camera_to_world": m.reshape(-1).tolist(), "fov": 50.0} for m in gl]}))
    out = tmp_path / "out"
    summary = morphgs.curate([folder], out, configs=["morphological"], pairs_per_scene=1, frames=5,
                             resolution=(cams.width, cams.height), depth=True, chunk=2, progress=False)
    assert summary.ok and summary.done == 1, summary.text()
    rec = summary.records[0]
    d = out / rec["paths"]["dir"]
    path = morphgs.Cameras.from_dict(json.loads((d / "cameras.json").read_text()))
    loaded = morphgs.load(folder / "scene.ply")
    renders = morphgs.render_many([loaded, morphgs.perturb(loaded, "morphological", seed=rec["seed"])], path)
    for side, r in zip(("clean", "corrupted"), renders):
        pngs = _core._read_png_batch(sorted((d / side).glob("*.png")))
        np.testing.assert_array_equal(np.stack([p for p, _ in pngs]), r.to_uint8(), err_msg=side)
        depth = _core._read_exr_batch(sorted((d / side).glob("*.depth.exr")))
        np.testing.assert_array_equal(np.stack(depth).view(np.uint32), r.depth.view(np.uint32), err_msg=side)
