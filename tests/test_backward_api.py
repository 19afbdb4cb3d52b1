"""`_core.DiffRasterizer`, the native differentiable rasterizer: its forward is `render`'s,
its densification statistics follow gsplat's DefaultStrategy, and bad input is a clear
ValueError (never a panic or a silent wrong answer)."""

from __future__ import annotations

import numpy as np
import pytest

import morphgs
from backward_reference import Params, Setup, front_camera, loss_weights, random_scene, rust_forward
from morphgs._core import DiffRasterizer


def test_forward_gives_render_bits_and_reuses_its_buffers() -> None:
    scene = random_scene(500, 2, seed=1)
    cam = front_camera(50, 38)
    p = Params.of(scene)
    want = morphgs.render(scene, cam, background=(0.1, 0.2, 0.3))
    r = DiffRasterizer()
    for _ in range(2):  # a second call on the same rasterizer reuses the buffers
        rgb, depth, alpha, stats = r.forward(*p.arrays(), cam.world_to_camera, cam.K, 50, 38,
                                             background=(0.1, 0.2, 0.3))
        assert rgb.tobytes() == want.rgb.tobytes()
        assert depth.tobytes() == want.depth.tobytes()
        assert alpha.tobytes() == want.alpha.tobytes()
        assert stats["evaluations"] == want.stats["evaluations"]


def test_densification_statistics_follow_gsplat() -> None:
    scene = random_scene(400, 0, seed=2)
    setup = Setup(front_camera(48, 32))
    cam = setup.cam
    p = Params.of(scene)
    r = DiffRasterizer()
    r.forward(*p.arrays(), cam.world_to_camera, cam.K, 48, 32)
    w = loss_weights(setup, seed=3)
    g = r.backward(*p.arrays(), v_rgb=w["rgb"], view=True, cameras_per_step=2.0)
    radii = r.projection()["radii"]
    vis = (radii > 0).all(axis=1)
    np.testing.assert_array_equal(g["count"], vis.astype(np.float32))
    scaled = g["means2d"] * np.array([48 / 2, 32 / 2]) * 2.0  # gsplat: x W/2, y H/2, x n_cameras
    np.testing.assert_allclose(g["grad2d"], np.linalg.norm(scaled, axis=1), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(g["max_radius"], radii.max(axis=1) / 48, rtol=1e-6)
    # absgrad was not asked for at forward: zero; with it, the sum of absolute per-pixel values
    # is at least the absolute sum
    assert not g["grad2d_abs"].any() and not g["means2d_abs"].any()
    r, _ = rust_forward(p, setup)  # absgrad on
    a = r.backward(*p.arrays(), v_rgb=w["rgb"], view=True, cameras_per_step=2.0)
    assert np.all(a["means2d_abs"] >= np.abs(a["means2d"]) * (1 - 1e-5))
    assert a["grad2d_abs"][vis].min() > 0


def test_bad_input_raises_value_errors() -> None:
    scene = random_scene(50, 0, seed=3)
    cam = front_camera(32, 24)
    p = Params.of(scene)
    r = DiffRasterizer()
    with pytest.raises(ValueError, match="forward"):
        r.backward(*p.arrays())
    with pytest.raises(ValueError, match="forward"):
        r.projection()
    r.forward(*p.arrays(), cam.world_to_camera, cam.K, 32, 24)
    with pytest.raises(ValueError, match="rgb gradient"):
        r.backward(*p.arrays(), v_rgb=np.zeros((24, 31, 3), np.float32))
    other = Params.of(random_scene(49, 0, seed=4))
    with pytest.raises(ValueError, match="49 Gaussians"):
        r.backward(*other.arrays())
    with pytest.raises(ValueError, match="C-contiguous"):
        r.backward(*p.arrays(), v_alpha=np.zeros((32, 24), np.float32).T)
    with pytest.raises(ValueError, match="sh_rest"):
        r.forward(*p.arrays()[:5], np.zeros((50, 5, 3), np.float32), cam.world_to_camera, cam.K,
                  32, 24)
    with pytest.raises(ValueError, match="depth"):
        r.forward(*p.arrays(), cam.world_to_camera, cam.K, 32, 24, depth="median")
    with pytest.raises(ValueError, match="colors"):
        r.forward(*p.arrays(), cam.world_to_camera, cam.K, 32, 24,
                  colors=np.zeros((49, 3), np.float32))
    with pytest.raises(ValueError, match="max_alpha"):
        r.forward(*p.arrays(), cam.world_to_camera, cam.K, 32, 24, max_alpha=0.0)
