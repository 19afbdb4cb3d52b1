"""The built-in synthetic scene: exact size, determinism, extent, and the statistics that make its
renders look like a capture (surface-aligned flat Gaussians, spread of scales and opacities,
view-dependent colour)."""

from __future__ import annotations

import numpy as np
import pytest

import morphgs
from morphgs import synthetic

FIELDS = ["means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest"]


@pytest.fixture(scope="module")
def big() -> morphgs.GaussianScene:
    return synthetic.scene(60_000, sh_degree=3, seed=0)


@pytest.mark.parametrize("n", [0, 1, 2, 9, 10, 11, 999, 12_345])
def test_exact_gaussian_count(n: int) -> None:
    s = synthetic.scene(n, sh_degree=1)
    assert len(s) == n and s.sh_rest.shape == (n, 3, 3)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sh_degree(degree: int) -> None:
    s = synthetic.scene(500, sh_degree=degree)
    k = (degree + 1) ** 2 - 1
    assert s.sh_degree == degree and s.sh_rest.shape == (500, k, 3)
    if k:
        assert np.abs(s.sh_rest).mean() > 1e-3  # view-dependent colour


def test_same_seed_same_scene_and_different_seed_different_scene() -> None:
    a, b = synthetic.scene(5000, seed=7), synthetic.scene(5000, seed=7)
    c = synthetic.scene(5000, seed=8)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert not np.array_equal(a.means, c.means)


def test_everything_inside_the_documented_extent(big: morphgs.GaussianScene) -> None:
    lo, hi = big.bounds()
    assert np.all(lo >= np.float32(synthetic.EXTENT_MIN)) and np.all(hi <= np.float32(synthetic.EXTENT_MAX))
    # it reaches the walls and the floor, and the content is concentrated near the origin
    assert hi[2] > 2.5 and lo[0] < -3.5 and hi[1] > 3.5
    near = np.linalg.norm(big.means[:, :2], axis=1) < 2.0
    assert near.mean() > 0.35


def test_values_are_finite_and_quats_unit(big: morphgs.GaussianScene) -> None:
    for f in FIELDS:
        assert np.isfinite(getattr(big, f)).all(), f
    np.testing.assert_allclose(np.linalg.norm(big.quats, axis=1), 1, atol=1e-6)


def _rotate_z_axis(q: np.ndarray) -> np.ndarray:
    """Third column of the rotation matrix of (w,x,y,z) quaternions: where local z goes."""
    w, x, y, z = q.T.astype(np.float64)
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1)


def test_floor_gaussians_are_flat_with_the_thin_axis_vertical(big: morphgs.GaussianScene) -> None:
    floor = big.means[:, 2] < 0.02
    assert floor.mean() > 0.2
    scales = big.scales[floor]
    assert np.median(scales[:, 2] / scales[:, :2].min(axis=1)) < 0.2  # flat
    normal = _rotate_z_axis(big.quats[floor])
    assert np.median(np.abs(normal[:, 2])) > 0.999


def test_back_wall_gaussians_face_the_room(big: morphgs.GaussianScene) -> None:
    wall = (big.means[:, 1] > 3.99) & (big.means[:, 2] > 0.3)
    assert wall.sum() > 1000
    normal = _rotate_z_axis(big.quats[wall])
    assert np.median(np.abs(normal[:, 1])) > 0.999


def test_scales_spread_log_normally(big: morphgs.GaussianScene) -> None:
    ls = big.log_scales[:, 0]
    p5, p50, p95 = np.percentile(ls, [5, 50, 95])
    assert 0.5 < p95 - p5 < 4.0  # neither constant nor absurd (about e^0.5 .. e^4)
    assert -6.0 < p50 < -2.0  # a few mm to a few cm at 60k Gaussians


def test_opacities_mostly_high_with_a_faint_tail(big: morphgs.GaussianScene) -> None:
    a = big.opacities
    assert np.median(a) > 0.85
    assert 0.05 < (a < 0.4).mean() < 0.3
    assert a.min() > 0 and a.max() < 1


def test_colours_vary_like_textures(big: morphgs.GaussianScene) -> None:
    c = big.colors
    assert c.min() >= 0 and c.max() <= 1
    assert c.std(axis=0).min() > 0.1  # textured, not flat
    # the floor has checker tiles: two clearly different tones
    floor = (big.means[:, 2] < 0.02) & (np.abs(big.means[:, 0]) > 2.7)
    lum = c[floor].mean(axis=1)
    assert np.percentile(lum, 90) - np.percentile(lum, 10) > 0.1


def test_a_few_floaters_in_the_air(big: morphgs.GaussianScene) -> None:
    m = big.means
    air = (m[:, 2] > 1.7) & (np.abs(m[:, 0]) < 3.5) & (np.abs(m[:, 1]) < 3.5)
    assert 0.001 < air.mean() < 0.02
    assert np.median(big.opacities[air]) < 0.3


def test_suggested_orbit_stays_in_the_room_and_sees_the_objects() -> None:
    orbit = synthetic.suggested_orbit()
    for angle in np.linspace(0, 2 * np.pi, 16, endpoint=False):
        eye = orbit.eye(angle)
        assert np.all(np.abs(eye[:2]) < 3.9) and 0 < eye[2] < 3
        assert np.linalg.norm(eye[:2] - np.array(orbit.center[:2])) == pytest.approx(orbit.radius)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="n_gaussians"):
        synthetic.scene(-1)
    with pytest.raises(ValueError, match="sh_degree"):
        synthetic.scene(10, sh_degree=5)
