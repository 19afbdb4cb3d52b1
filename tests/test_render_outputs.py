"""The arrays a render returns: their memory is reused from released renders (a process-wide
pool of bounded size), yet a Render's arrays stay valid and unshared for as long as Python holds
them, or any view of them."""

from __future__ import annotations

import gc

import numpy as np

import morphgs
from morphgs import synthetic, trajectory


def _scene_and_path(frames: int, size: tuple[int, int]) -> tuple[morphgs.GaussianScene, morphgs.Cameras]:
    scene = synthetic.scene(n_gaussians=3000, sh_degree=1, seed=11)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], frames, fov_y_degrees=50.0,
                            resolution=size)
    return scene, cams


def _arrays(r: morphgs.Render) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return r.rgb, r.depth, r.alpha


def _bits(r: morphgs.Render) -> tuple[bytes, bytes, bytes]:
    return r.rgb.tobytes(), r.depth.tobytes(), r.alpha.tobytes()


def test_held_renders_keep_their_values_while_later_renders_reuse_released_memory() -> None:
    scene, cams = _scene_and_path(4, (72, 48))
    _, small = _scene_and_path(2, (40, 24))
    held = [morphgs.render(scene, cams[i]) for i in range(4)]
    held += morphgs.render_many([scene, scene], small)  # (F,H,W) renders of another size
    want = [_bits(r) for r in held]
    view = held[0].rgb[5:9, 3]  # a view outlives its Render
    view_bits = view.tobytes()
    del held[0]
    gc.collect()
    # renders released one after another: their memory goes round and round
    reused = set()
    for k in range(12):
        r = morphgs.render(scene, cams[k % 4])
        assert _bits(r) == _bits(morphgs.render(scene, cams[k % 4]))
        reused.add(r.rgb.__array_interface__["data"][0])
        for a in _arrays(r):  # poison it: the next render into this memory writes every value
            a.fill(np.nan)
        del r
        morphgs.render_many([scene], small)
    assert len(reused) < 12  # released memory was taken again
    assert [_bits(r) for r in held] == want[1:]
    assert view.tobytes() == view_bits
    # no two live arrays share memory
    live = [a for r in held for a in _arrays(r)] + [view.base if view.base is not None else view]
    fresh = morphgs.render(scene, cams[0])
    live += list(_arrays(fresh))
    for i, a in enumerate(live):
        for b in live[i + 1:]:
            assert not np.shares_memory(a, b)


def test_returned_arrays_are_writable_float32_and_equal_a_fresh_render_after_reuse() -> None:
    scene, cams = _scene_and_path(2, (64, 40))
    first = morphgs.render(scene, cams)
    want = _bits(first)
    assert first.rgb.dtype == np.float32 and first.rgb.shape == (2, 40, 64, 3)
    assert first.rgb.flags.writeable and first.depth.flags.c_contiguous
    first.rgb[...] = -1.0  # the caller may write into its arrays
    del first
    gc.collect()
    again = morphgs.render(scene, cams)
    assert _bits(again) == want
