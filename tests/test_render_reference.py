"""The rasterizer against gsplat 1.5.3's pure-PyTorch projection/SH and a float64 blend
(SPEC §4), within SPEC tolerances: projection radii +-1 and rtol = atol = 1e-4; images mean
absolute error <= 1e-5 and 99.9th percentile <= 1e-3.

Fixtures: tests/fixtures (see its ATTRIBUTION.md). The garden images are compared on a
176x112 window of each full-resolution (648x420) view, so the float64 reference stays quick.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs._core import _project

pytest.importorskip("torch")
pytest.importorskip("gsplat")

from render_reference import garden, gsplat_project, reference_blend  # noqa: E402

FIXTURE_PLYS = ["metalsplatter_train3.ply", "splatapult_test.ply"]


def project(scene: morphgs.GaussianScene, cam: morphgs.Camera, **kw: object) -> dict[str, np.ndarray]:
    return _project(scene, cam.world_to_camera, cam.K, cam.width, cam.height,
                    near=cam.near, far=cam.far, **kw)


def assert_projection_matches(scene: morphgs.GaussianScene, cam: morphgs.Camera, **kw: object) -> int:
    """Compare with gsplat; returns how many Gaussians both keep."""
    got = project(scene, cam, **kw)
    ref = gsplat_project(scene, cam, **kw)  # type: ignore[arg-type]
    ours = (got["radii"] > 0).all(axis=1)
    theirs = (ref.radii > 0).all(axis=1)
    both = ours & theirs
    # visibility may only differ where a radius sits within one pixel of a decision boundary
    differ = np.nonzero(ours != theirs)[0]
    assert len(differ) <= max(1, len(scene) // 1000), f"visibility differs for {len(differ)} Gaussians"
    np.testing.assert_allclose(got["radii"][both], ref.radii[both], atol=1, rtol=0)
    for name, want in [("means2d", ref.means2d), ("depths", ref.depths), ("conics", ref.conics),
                       ("opacities", ref.opacities), ("colors", ref.colors)]:
        np.testing.assert_allclose(got[name][both], want[both], rtol=1e-4, atol=1e-4, err_msg=name)
    return int(both.sum())


def assert_images_match(scene: morphgs.GaussianScene, cam: morphgs.Camera, *,
                        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                        max_alpha: float = 0.99, **kw: object) -> morphgs.Render:
    r = morphgs.render(scene, cam, background=background, max_alpha=max_alpha, **kw)  # type: ignore[arg-type]
    ref = gsplat_project(scene, cam, **kw)  # type: ignore[arg-type]
    rgb, depth, alpha = reference_blend(ref, cam.width, cam.height, background=background,
                                        max_alpha=max_alpha)
    for name, got, want in [("rgb", r.rgb, rgb), ("alpha", r.alpha, alpha)]:
        err = np.abs(got.astype(np.float64) - want)
        assert err.mean() <= 1e-5, f"{name}: mean abs error {err.mean():.3g}"
        assert np.quantile(err, 0.999) <= 1e-3, f"{name}: p99.9 error {np.quantile(err, 0.999):.3g}"
    # expected depth: relative to the scene depth, where there is coverage
    cover = alpha > 0.05
    if cover.any():
        derr = np.abs(r.depth[cover] - depth[cover]) / np.maximum(depth[cover], 1e-6)
        assert np.quantile(derr, 0.999) <= 1e-3 and derr.mean() <= 1e-4
    assert np.all(np.isfinite(r.rgb)) and np.all(np.isfinite(r.depth))
    return r


def random_scene(n: int, degree: int, seed: int, *, spread: float = 1.0,
                 log_scale: tuple[float, float] = (-4.0, -1.5)) -> morphgs.GaussianScene:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return morphgs.GaussianScene.from_arrays(
        means=rng.uniform(-spread, spread, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(*log_scale, (n, 3)),
        opacity_logits=rng.normal(0.0, 2.0, n),
        sh0=rng.normal(0.0, 0.8, (n, 3)),
        sh_rest=rng.normal(0.0, 0.3, (n, k, 3)) if degree else None,
    )


def front_camera(width: int = 96, height: int = 64, *, distance: float = 4.0,
                 cx: float | None = None, cy: float | None = None) -> morphgs.Camera:
    c2w = np.eye(4)
    c2w[2, 3] = -distance  # at z = -distance looking along +z
    return morphgs.Camera.from_c2w(c2w, fx=1.1 * width, fy=1.1 * width, width=width, height=height,
                                   cx=cx, cy=cy)


# ---- projection ----

@pytest.mark.parametrize("name", FIXTURE_PLYS)
def test_projection_of_fixture_plys_matches_gsplat(fixtures_dir: Path, name: str) -> None:
    scene = morphgs.load(fixtures_dir / name)
    lo, hi = scene.bounds()
    centre = (lo + hi) / 2
    radius = float(np.max(hi - lo)) + 0.5
    kept = 0
    for eye in ([0.1, -0.2, 1], [1, 0.3, 0.2], [-0.5, -1, 0.4]):
        cam = morphgs.Camera.look_at(centre + radius * np.asarray(eye, float), centre,
                                     fov_y_degrees=60, width=160, height=120)
        kept += assert_projection_matches(scene, cam)
    assert kept > 0


def test_projection_of_garden_matches_gsplat_for_its_three_cameras(fixtures_dir: Path) -> None:
    scene, cams = garden(fixtures_dir)
    for cam in cams:
        assert assert_projection_matches(scene, cam) > 50_000


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_projection_and_sh_of_random_scenes_match_gsplat(degree: int) -> None:
    scene = random_scene(3000, degree, seed=degree)
    cam = front_camera(120, 80)
    assert assert_projection_matches(scene, cam) > 1000
    if degree:
        assert_projection_matches(scene, cam, sh_degree=degree - 1)


def test_projection_antialiased_matches_gsplat_compensation() -> None:
    scene = random_scene(2000, 1, seed=7, log_scale=(-7.0, -3.0))
    assert assert_projection_matches(scene, front_camera(), antialiased=True) > 500


# ---- images ----

@pytest.mark.parametrize("name", FIXTURE_PLYS)
def test_fixture_renders_match_reference_blend(fixtures_dir: Path, name: str) -> None:
    scene = morphgs.load(fixtures_dir / name)
    lo, hi = scene.bounds()
    centre = (lo + hi) / 2
    radius = float(np.max(hi - lo)) + 0.5
    cam = morphgs.Camera.look_at(centre + radius * np.array([0.2, -0.3, 1.0]), centre,
                                 fov_y_degrees=60, width=160, height=112)
    r = assert_images_match(scene, cam)
    assert r.alpha.max() > 0.1


def test_garden_renders_match_reference_blend_for_its_three_cameras(fixtures_dir: Path) -> None:
    scene, cams = garden(fixtures_dir)
    for cam in cams:
        # a 176x112 window of the full-resolution image at pixel (232, 150)
        crop = morphgs.Camera(cam.fx, cam.fy, cam.cx - 232, cam.cy - 150, 176, 112,
                              cam.world_to_camera)
        r = assert_images_match(scene, crop)
        assert r.alpha.mean() > 0.5


@pytest.mark.parametrize("degree", [0, 3])
@pytest.mark.parametrize("max_alpha", [0.99, 0.999])
def test_random_scenes_match_reference_blend(degree: int, max_alpha: float) -> None:
    scene = random_scene(4000, degree, seed=10 + degree)
    assert_images_match(scene, front_camera(100, 70), max_alpha=max_alpha,
                        background=(0.2, 0.5, 1.0))


def test_antialiased_render_matches_reference_blend() -> None:
    scene = random_scene(3000, 0, seed=3, log_scale=(-7.0, -2.5))
    assert_images_match(scene, front_camera(), antialiased=True)


def test_lower_sh_degree_matches_reference_blend() -> None:
    scene = random_scene(2000, 3, seed=5)
    assert_images_match(scene, front_camera(), sh_degree=1)


def test_hard_cases_match_reference_blend() -> None:
    """Behind the camera, straddling the near plane, huge and tiny, partly off-screen Gaussians,
    on a non-square image with an off-centre principal point."""
    rng = np.random.default_rng(42)
    means = [
        [0.0, 0.0, -5.0],     # behind the camera (camera at z=-4 looking +z)
        [0.1, 0.0, -3.995],   # centre just past the near plane, large: straddles it
        [0.0, 0.1, -4.0 + 0.02],
        [0.0, 0.0, 2.0],      # huge
        [0.3, -0.2, 0.0],     # tiny
        [2.5, 0.0, 1.0],      # partly off-screen right
        [-1.2, 1.0, 0.5],     # partly off-screen bottom-left
        [0.0, -30.0, 1.0],    # far off-screen
    ]
    log_scales = [[-1, -1, -1], [-2.0, -2.0, -2.0], [-3, -3, -3], [1.5, 1.2, 0.5],
                  [-9, -9, -9], [-0.5, -0.5, -0.5], [-0.7, -1.5, -0.6], [0, 0, 0]]
    n = len(means)
    extra = random_scene(500, 0, seed=1)
    scene = morphgs.GaussianScene.from_arrays(
        means=np.vstack([means, extra.means]),
        quats=np.vstack([rng.normal(size=(n, 4)), extra.quats]),
        log_scales=np.vstack([log_scales, extra.log_scales]),
        opacity_logits=np.concatenate([np.full(n, 2.0), extra.opacity_logits]),
        sh0=np.vstack([rng.normal(0, 1, (n, 3)), extra.sh0]),
    )
    cam = front_camera(123, 77, cx=40.0, cy=50.5)
    assert_projection_matches(scene, cam)
    for max_alpha in (0.99, 0.999):
        assert_images_match(scene, cam, max_alpha=max_alpha, background=(1.0, 1.0, 1.0))
    tall = front_camera(48, 100, distance=3.0, cx=30.0, cy=20.0)
    assert_images_match(scene, tall)


def test_max_alpha_caps_opaque_gaussians_as_the_reference_does() -> None:
    rng = np.random.default_rng(4)
    n = 60
    scene = morphgs.GaussianScene.from_arrays(
        means=rng.uniform(-0.8, 0.8, (n, 3)), quats=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(-2.5, -1.0, (n, 3)), opacity_logits=np.full(n, 12.0),
        sh0=rng.normal(0, 1, (n, 3)),
    )
    cam = front_camera(80, 60)
    lo = assert_images_match(scene, cam, max_alpha=0.99, background=(0.0, 1.0, 0.0))
    hi = assert_images_match(scene, cam, max_alpha=0.999, background=(0.0, 1.0, 0.0))
    # the cap decides how much background shows through fully covered pixels
    assert np.abs(lo.rgb - hi.rgb).max() > 1e-3


def test_off_screen_centres_whose_boxes_reach_in_are_kept_exactly() -> None:
    """Centres outside the image with boxes reaching into it (the projection's early out must
    never drop them), for a rigid and for a scaled (non-rigid) world-to-camera matrix."""
    rng = np.random.default_rng(8)
    n = 3000
    ang = rng.uniform(0, 2 * np.pi, n)
    rad = rng.uniform(0.9, 2.0, n)
    means = np.stack([rad * np.cos(ang) * 1.6, rad * np.sin(ang) * 1.1, rng.uniform(-0.5, 0.5, n)], 1)
    scene = morphgs.GaussianScene.from_arrays(
        means=means, quats=rng.normal(size=(n, 4)), log_scales=rng.uniform(-4, -0.5, (n, 3)),
        opacity_logits=rng.normal(0, 2, n), sh0=rng.normal(0, 1, (n, 3)))
    cam = front_camera(96, 64, distance=3.0)
    for w2c in (cam.world_to_camera, cam.world_to_camera @ np.diag([1.7, 0.6, 1.2, 1.0])):
        c = morphgs.Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, w2c)
        got = project(scene, c)
        ref = gsplat_project(scene, c)
        kept = (ref.radii > 0).all(axis=1)
        assert 100 < kept.sum() < n
        np.testing.assert_array_equal((got["radii"] > 0).all(axis=1), kept)
