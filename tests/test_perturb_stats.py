"""Statistics of every perturbation on 200k Gaussians (SPEC §2): the realised noise has the
formula's mean and standard deviation, pruning keeps 1 - p, clamps hold, seeds are independent."""

from __future__ import annotations

import math

import numpy as np
import pytest

import morphgs
from morphgs import PerturbConfig

N = 200_000
C0 = 0.28209479177387814
OFF = dict.fromkeys(
    ("position_jitter", "color_noise", "opacity_noise", "prune", "scale_noise", "rotation_noise")
)


def only(**ops: float) -> PerturbConfig:
    return PerturbConfig(**{**OFF, **ops})


@pytest.fixture(scope="module")
def mid_scene() -> morphgs.GaussianScene:
    """Inputs where no clamp bites: colours and opacities 0.5, unit scales, identity rotations."""
    rng = np.random.default_rng(1)
    return morphgs.GaussianScene.from_arrays(
        means=rng.uniform(-4.0, 6.0, size=(N, 3)),
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (N, 1)),
        log_scales=np.zeros((N, 3)),
        opacity_logits=np.zeros(N),
        sh0=np.zeros((N, 3)),
        sh_rest=rng.normal(size=(N, 3, 3)),
    )


def assert_normal(eps: np.ndarray, sigma: float, what: str) -> None:
    """Mean within 4 sigma/sqrt(n), standard deviation within 2% (per column)."""
    eps = np.asarray(eps, dtype=np.float64).reshape(len(eps), -1)
    n = eps.shape[0]
    mean, sd = eps.mean(axis=0), eps.std(axis=0, ddof=1)
    assert np.all(np.abs(mean) < 4 * sigma / math.sqrt(n)), f"{what}: mean {mean}, sigma {sigma}"
    assert np.all(np.abs(sd / sigma - 1) < 0.02), f"{what}: std {sd}, want {sigma}"


def test_position_jitter_is_normal_with_sigma_gamma_times_mean_extent(mid_scene) -> None:
    out = morphgs.perturb(mid_scene, only(position_jitter=0.002), seed=3)
    m = mid_scene.means.astype(np.float64)
    e_avg = (m.max(axis=0) - m.min(axis=0)).mean()
    assert_normal(out.means.astype(np.float64) - m, 0.002 * e_avg, "position")


def test_color_noise_is_normal_on_the_dc_colour_and_leaves_higher_bands(mid_scene) -> None:
    out = morphgs.perturb(mid_scene, only(color_noise=0.05), seed=3)
    assert_normal(out.colors.astype(np.float64) - mid_scene.colors, 0.05, "colour")
    np.testing.assert_array_equal(out.sh_rest, mid_scene.sh_rest)


def test_opacity_noise_is_normal_in_activated_space(mid_scene) -> None:
    out = morphgs.perturb(mid_scene, only(opacity_noise=0.05), seed=3)
    assert_normal(out.opacities.astype(np.float64) - mid_scene.opacities, 0.05, "opacity")


def test_scale_noise_is_normal_on_linear_scales(mid_scene) -> None:
    out = morphgs.perturb(mid_scene, only(scale_noise=0.01), seed=3)
    assert_normal(np.exp(out.log_scales.astype(np.float64)) - 1.0, 0.01, "scale")


def test_rotation_noise_is_normal_on_the_quaternion_then_renormalised(mid_scene) -> None:
    out = morphgs.perturb(mid_scene, only(rotation_noise=0.01), seed=3)
    q = out.quats.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    # q' = (1 + e0, e1, e2, e3) / norm, so q'_k / q'_0 = e_k / (1 + e0): sd sigma*sqrt(1+sigma^2)
    assert_normal(q[:, 1:] / q[:, :1], 0.01, "rotation")
    assert np.all(q[:, 0] > 0.9)


@pytest.mark.parametrize("p", [0.5, 0.3, 0.9])
def test_pruning_keeps_a_binomial_fraction(mid_scene, p: float) -> None:
    out, mask = morphgs.perturb(mid_scene, only(prune=p), seed=5, return_mask=True)
    kept = int(mask.sum())
    assert len(out) == kept and mask.shape == (N,) and mask.dtype == np.bool_
    sd = math.sqrt(N * p * (1 - p))
    assert abs(kept - N * (1 - p)) < 4 * sd, f"kept {kept} of {N} at p={p}"


def test_prune_zero_keeps_all_and_one_removes_all(mid_scene) -> None:
    assert len(morphgs.perturb(mid_scene, only(prune=0.0), seed=1)) == N
    empty = morphgs.perturb(mid_scene, only(prune=1.0), seed=1)
    assert len(empty) == 0 and empty.sh_rest.shape == (0, 3, 3)


def test_noise_before_the_clamp_is_normal_where_clamps_bite() -> None:
    """At colour 0 and scale floor 1e-6 half the draws are clamped; the other half must be the
    positive half of N(0, sigma^2): mean sigma*sqrt(2/pi), std sigma*sqrt(1 - 2/pi)."""
    n = N
    scene = morphgs.GaussianScene.from_arrays(
        means=np.zeros((n, 3)),
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        log_scales=np.full((n, 3), np.log(np.float32(1e-6))),
        opacity_logits=np.zeros(n),
        sh0=np.full((n, 3), -0.5 / C0),
    )
    out = morphgs.perturb(scene, only(color_noise=0.05, scale_noise=0.01), seed=11)
    for values, sigma, floor in ((out.colors, 0.05, 0.0), (out.scales, 0.01, 1e-6)):
        v = values.astype(np.float64).ravel() - floor
        clamped = np.mean(v <= 1e-9)
        assert abs(clamped - 0.5) < 4 * math.sqrt(0.25 / v.size)
        pos = v[v > 1e-9]
        half_mean, half_sd = sigma * math.sqrt(2 / math.pi), sigma * math.sqrt(1 - 2 / math.pi)
        assert abs(pos.mean() - half_mean) < 4 * half_sd / math.sqrt(pos.size)
        assert abs(pos.std() / half_sd - 1) < 0.02


def test_clamps_hold_on_inputs_where_they_bite() -> None:
    rng = np.random.default_rng(2)
    n = N
    scene = morphgs.GaussianScene.from_arrays(
        means=rng.normal(size=(n, 3)),
        quats=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(-20, -10, size=(n, 3)),
        opacity_logits=rng.choice([-40.0, -9.0, 9.0, 40.0], size=n),
        sh0=rng.choice([-10.0, -1.77, 1.77, 10.0], size=(n, 3)),
    )
    cfg = PerturbConfig(
        position_jitter=0.01, color_noise=0.3, opacity_noise=0.3, prune=None,
        scale_noise=0.05, rotation_noise=3.0,
    )
    out = morphgs.perturb(scene, cfg, seed=4)
    assert np.all((out.colors >= 0) & (out.colors <= 1))
    op = out.opacities
    assert np.all((op >= np.float32(1e-4)) & (op <= np.float32(1 - 1e-4)))
    assert np.all(out.scales >= np.float32(1e-6))
    np.testing.assert_allclose(np.linalg.norm(out.quats.astype(np.float64), axis=1), 1.0, atol=1e-6)
    # the clamps really bit
    assert np.mean(out.colors == 0) > 0.1 and np.mean(out.scales < np.float32(1.01e-6)) > 0.1


def test_two_seeds_give_uncorrelated_noise(mid_scene) -> None:
    cfg = only(color_noise=0.05, position_jitter=0.002)
    a = morphgs.perturb(mid_scene, cfg, seed=1)
    b = morphgs.perturb(mid_scene, cfg, seed=2)
    bound = 4 / math.sqrt(N)
    for field in ("colors", "means"):
        ea = (getattr(a, field).astype(np.float64) - getattr(mid_scene, field))[:, 0]
        eb = (getattr(b, field).astype(np.float64) - getattr(mid_scene, field))[:, 0]
        corr = np.corrcoef(ea, eb)[0, 1]
        assert abs(corr) < bound, f"{field}: corr {corr}"
    # and the ops of one seed are uncorrelated with each other
    both = morphgs.perturb(mid_scene, only(color_noise=0.05, opacity_noise=0.05), seed=1)
    ec = both.colors[:, 0].astype(np.float64) - 0.5
    eo = both.opacities.astype(np.float64) - 0.5
    assert abs(np.corrcoef(ec, eo)[0, 1]) < bound
