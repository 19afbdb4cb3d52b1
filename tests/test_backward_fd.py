"""The backward pass against central finite differences in float64 on tiny scenes holding the
forward tests' hard cases: a Gaussian straddling the near plane (its projection clamped by the
frustum limits), partly off-screen ones (clamped too), huge and tiny ones, alpha capped at
max_alpha, pixels stopping at T <= 1e-4, SH degree 0 and 3, a non-square image with an
off-centre principal point, the antialiased mode.

The differentiated function is the float64 reference of tests/backward_reference.py with the
Rust forward's blend decisions frozen (which pairs blend, which alphas are capped): where those
decisions do not change, it is the forward's function, so its finite differences are the
derivative the backward must give.
"""

from __future__ import annotations

import numpy as np
import pytest

import morphgs

torch = pytest.importorskip("torch")
pytest.importorskip("gsplat")

from backward_reference import (  # noqa: E402
    Params,
    Reference,
    Setup,
    front_camera,
    loss_weights,
    rust_backward,
    rust_forward,
)

STEP = 1e-6


def hard_scene(degree: int, seed: int) -> morphgs.GaussianScene:
    """Ten Gaussians in front of a camera at z = -4 looking along +z (near plane z = -3.99)."""
    rng = np.random.default_rng(seed)
    rows = [
        # mean, log scales, opacity logit
        ([0.0, 0.0, -3.978], [-3.2, -3.0, -3.4], 1.0),    # straddles the near plane, clamped J
        ([0.55, 0.05, -1.0], [-1.6, -1.8, -1.7], 0.5),    # centre off-screen right, part visible
        ([-0.1, -0.45, -0.5], [-2.0, -1.6, -2.2], 0.3),   # partly off-screen top
        ([0.05, 0.02, 0.0], [-2.4, -2.2, -2.6], 9.0),     # opaque: alpha capped near its centre
        ([0.1, 0.05, 0.5], [-1.5, -1.4, -1.6], 8.0),      # opaque layers behind it: T <= 1e-4
        ([-0.05, 0.0, 1.0], [-1.3, -1.5, -1.4], 8.0),
        ([0.0, 0.0, 3.0], [0.2, 0.1, 0.3], 2.0),          # huge, far
        ([-0.2, 0.15, -2.0], [-9.0, -9.0, -9.0], 3.0),    # tiny: eps2d dominates
        ([0.2, -0.2, -2.5], [-2.5, -3.0, -2.0], -0.5),
        ([-0.3, 0.25, 0.3], [-2.0, -2.1, -1.9], 0.0),
    ]
    n = len(rows)
    k = (degree + 1) ** 2 - 1
    return morphgs.GaussianScene.from_arrays(
        means=np.array([r[0] for r in rows]),
        quats=rng.normal(size=(n, 4)),
        log_scales=np.array([r[1] for r in rows]),
        opacity_logits=np.array([r[2] for r in rows]),
        sh0=rng.normal(0.0, 0.8, (n, 3)),
        sh_rest=rng.normal(0.0, 0.4, (n, k, 3)) if degree else None,
    )


def finite_differences(ref: Reference, p: Params, w: dict, vis: np.ndarray) -> dict[str, np.ndarray]:
    """Central differences of the float64 reference loss for every parameter of the visible
    Gaussians."""
    base = ref.tensors(p, requires_grad=False)
    out = {}
    with torch.no_grad():
        for name in p.names:
            t = base[name]
            g = np.zeros(t.shape)
            for i in np.nonzero(vis)[0]:
                for j in np.ndindex(t.shape[1:]):
                    idx = (i, *j)
                    keep = float(t[idx])
                    t[idx] = keep + STEP
                    up = float(ref.loss(base, w))
                    t[idx] = keep - STEP
                    down = float(ref.loss(base, w))
                    t[idx] = keep
                    g[idx] = (up - down) / (2 * STEP)
            out[name] = g
    return out


def check_against_fd(scene: morphgs.GaussianScene, setup: Setup, *, expect: dict[str, bool]) -> None:
    p = Params.of(scene)
    r, (_, _, alpha) = rust_forward(p, setup)
    w = loss_weights(setup, seed=17)
    ours = rust_backward(r, p, w)
    ref = Reference(p, setup, r)
    vis = (r.projection()["radii"] > 0).all(axis=1)
    assert vis.sum() >= 8, f"only {vis.sum()} of the hard cases visible"
    # the scene reaches the cases it is meant to
    if expect.get("capped"):
        assert ref.clamped.any(), "no alpha reached max_alpha"
    if expect.get("stopped"):
        # transmittance below 1e-3 after capped layers: the next layer stops the pixel
        assert (1.0 - alpha).min() < 1e-3, "no pixel reaches early termination"
    fd = finite_differences(ref, p, w, vis)
    for name in p.names:
        got, want = ours[name][vis], fd[name][vis]
        if want.size == 0:
            continue
        scale = float(np.abs(want).max())
        err = np.abs(got - want)
        # float32 gradients against float64 differences: 1e-3 of the largest, 1e-3 relative
        assert np.all(err <= 1e-3 * scale + 1e-3 * np.abs(want)), (
            f"{name}: max error {err.max():.3g} of {scale:.3g}")


@pytest.mark.parametrize("degree", [0, 3])
def test_hard_cases_match_finite_differences(degree: int) -> None:
    cam = front_camera(40, 28, cx=17.0, cy=15.5)
    check_against_fd(hard_scene(degree, seed=degree), Setup(cam, background=(0.3, 0.6, 0.9)),
                     expect={"capped": True, "stopped": True})


def test_hard_cases_match_finite_differences_antialiased_gsplat_max_alpha() -> None:
    cam = front_camera(36, 44, cx=20.0, cy=19.0)
    check_against_fd(hard_scene(1, seed=5), Setup(cam, max_alpha=0.999, antialiased=True),
                     expect={"stopped": True})


def test_early_termination_cuts_the_gradient_of_what_lies_behind() -> None:
    """Pixels stop at T <= 1e-4: a small Gaussian behind a stack of wide opaque layers gets no
    gradient, though it projects inside the image, while the front layers do."""
    n = 9
    means = [[0.0, 0.0, -1.0 + 0.2 * i] for i in range(8)] + [[0.02, 0.01, 2.0]]
    scene = morphgs.GaussianScene.from_arrays(
        means=np.array(means),
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        log_scales=np.array([[np.log(0.5)] * 3] * 8 + [[np.log(0.01)] * 3]),
        opacity_logits=np.full(n, 10.0),
        sh0=np.random.default_rng(0).normal(0, 0.5, (n, 3)),
    )
    setup = Setup(front_camera(40, 28, cx=17.0, cy=15.5))
    p = Params.of(scene)
    r, (_, _, alpha) = rust_forward(p, setup)
    g = rust_backward(r, p, loss_weights(setup, seed=2))
    assert (r.projection()["radii"] > 0).all()
    assert np.any(g["means"][0]) and np.any(g["sh0"][1])
    assert not np.any(g["means"][-1]) and not np.any(g["sh0"][-1])
    _, gid, _ = r.contributions()
    assert (n - 1) not in set(gid.tolist()), "the hidden Gaussian blended somewhere"
