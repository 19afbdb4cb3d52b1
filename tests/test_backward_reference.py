"""The backward pass against torch autograd through gsplat 1.5.3's pure-PyTorch projection and
SH (`gsplat.cuda._torch_impl`, CPU, float64) and a dense float64 blend over the Rust forward's
blended pairs (tests/backward_reference.py).

Each check holds at gsplat's own CUDA-vs-torch test tolerances (its tests/test_basic.py; see
docs/backward.md) and at a stricter one of ours: the largest error of each gradient is at most
1e-3 of that gradient's largest magnitude (typical errors are 1e-5 of it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs

pytest.importorskip("torch")
pytest.importorskip("gsplat")

from backward_reference import (  # noqa: E402
    Params,
    Reference,
    Setup,
    front_camera,
    loss_weights,
    random_scene,
    rust_backward,
    rust_forward,
)
from render_reference import garden  # noqa: E402

# gsplat 1.5.3 tests/test_basic.py (rtol, atol): projection, SH and rasterize VJPs
GSPLAT_TOL = {
    "means": (1e-2, 6e-2),
    "quats": (2e-1, 2e-2),
    "log_scales": (5e-1, 2e-1),
    "opacity_logits": (8e-3, 6e-3),
    "sh0": (1e-4, 1e-4),
    "sh_rest": (1e-4, 1e-4),
    "background": (1e-3, 1e-3),
    "means2d": (5e-3, 5e-3),
    "conics": (1e-3, 1e-3),
    "view_colors": (1e-3, 1e-3),
    "view_opacities": (8e-3, 6e-3),
}
# our view gradients and the reference's per-Gaussian projected values they correspond to
VIEW = {"means2d": "means2d", "conics": "conics", "view_colors": "colors",
        "view_opacities": "opacities", "view_depths": "depths"}
STRICT = 1e-3


def check(scene: morphgs.GaussianScene, setup: Setup, seed: int = 0) -> dict[str, float]:
    """Compare every gradient with the reference; returns the relative errors."""
    p = Params.of(scene)
    r, _ = rust_forward(p, setup)
    w = loss_weights(setup, seed)
    ours = rust_backward(r, p, w)
    want, inter = Reference(p, setup, r).grads(p, w)
    vis = (r.projection()["radii"] > 0).all(axis=1)
    assert vis.sum() > 0
    errors = {}
    pairs = [(n, ours[n], want[n]) for n in p.names] + [("background", ours["background"],
                                                         want["background"])]
    pairs += [(n, ours[n], inter[k]) for n, k in VIEW.items()]
    for name, got, ref in pairs:
        if name != "background":
            # culled Gaussians get exactly zero
            assert not np.any(got[~vis]), name
            got, ref = got[vis], ref[vis]
        if got.size == 0:
            continue
        scale = float(np.abs(ref).max())
        err = float(np.abs(got - ref).max())
        errors[name] = err / max(scale, 1e-30)
        assert err <= STRICT * scale + 1e-12, f"{name}: max error {err:.3g} of {scale:.3g}"
        if name in GSPLAT_TOL:
            rtol, atol = GSPLAT_TOL[name]
            np.testing.assert_allclose(got, ref, rtol=rtol, atol=atol, err_msg=name)
    return errors


@pytest.mark.parametrize("degree", [0, 3])
@pytest.mark.parametrize("max_alpha", [0.99, 0.999])
def test_gradients_match_autograd_of_gsplat_torch_reference(degree: int, max_alpha: float) -> None:
    scene = random_scene(300, degree, seed=degree + 7)
    errors = check(scene, Setup(front_camera(64, 48), max_alpha=max_alpha,
                                background=(0.2, 0.5, 1.0)))
    assert max(errors.values()) < 2e-4


def test_antialiased_gradients_match_reference() -> None:
    scene = random_scene(300, 1, seed=5, log_scale=(-7.0, -3.0))
    check(scene, Setup(front_camera(64, 48), antialiased=True))


def test_accumulated_depth_gradients_match_reference() -> None:
    scene = random_scene(250, 2, seed=9)
    check(scene, Setup(front_camera(56, 40), depth="accumulated"), seed=3)


def test_lower_sh_degree_leaves_higher_bands_without_gradient() -> None:
    scene = random_scene(200, 3, seed=4)
    setup = Setup(front_camera(48, 40), sh_degree=1)
    check(scene, setup)
    p = Params.of(scene)
    r, _ = rust_forward(p, setup)
    g = rust_backward(r, p, loss_weights(setup, 1))
    assert np.any(g["sh_rest"][:, :3]) and not np.any(g["sh_rest"][:, 3:])


def test_non_square_off_centre_camera_gradients_match_reference() -> None:
    scene = random_scene(300, 1, seed=12, spread=1.5)
    check(scene, Setup(front_camera(37, 71, cx=10.0, cy=50.5), background=(1.0, 1.0, 1.0)))


def test_garden_window_gradients_match_reference(fixtures_dir: Path) -> None:
    """The real garden scene with its first camera, on an 80x56 window of the full view."""
    scene, cams = garden(fixtures_dir)
    cam = cams[0]
    crop = morphgs.Camera(cam.fx, cam.fy, cam.cx - 280, cam.cy - 180, 80, 56,
                          cam.world_to_camera)
    errors = check(scene, Setup(crop, max_alpha=0.999))
    assert max(errors.values()) < 2e-4
