"""render_pair: one load, one perturbation, both sequences along the same cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import synthetic, trajectory


@pytest.fixture(scope="module")
def scene() -> morphgs.GaussianScene:
    return synthetic.scene(n_gaussians=4000, sh_degree=3, seed=1)


@pytest.fixture(scope="module")
def cams() -> morphgs.Cameras:
    o = synthetic.suggested_orbit()
    return trajectory.orbit(o.center, o.radius, o.height - o.center[2], 3, start_degrees=150,
                            arc_degrees=40, resolution=(48, 32))


def test_pair_is_the_render_of_the_scene_and_of_its_seeded_perturbation(scene, cams) -> None:
    pair = morphgs.render_pair(scene, cams, config="morphological", seed=7)
    clean = morphgs.render(scene, cams)
    corrupted = morphgs.render(morphgs.perturb(scene, "morphological", seed=7), cams)
    np.testing.assert_array_equal(pair.clean.rgb, clean.rgb)
    np.testing.assert_array_equal(pair.clean.depth, clean.depth)
    np.testing.assert_array_equal(pair.corrupted.rgb, corrupted.rgb)
    np.testing.assert_array_equal(pair.corrupted.depth, corrupted.depth)
    assert pair.clean.rgb.shape == (3, 32, 48, 3)
    assert pair.seed == 7 and pair.cameras is cams
    assert pair.config == morphgs.PerturbConfig.preset("morphological").to_dict()
    assert not np.array_equal(pair.clean.rgb, pair.corrupted.rgb)


@pytest.mark.parametrize("config", ["spatial", "radiometric", "naive"])
def test_pair_colours_shared_between_the_scenes_change_no_byte(scene, cams, config: str) -> None:
    # the corrupted render takes the clean render's colours of Gaussians whose mean and SH it
    # kept; spatial noise moves means and radiometric noise changes SH: those compute their own
    pair = morphgs.render_pair(scene, cams, config=config, seed=3)
    corrupted = morphgs.render(morphgs.perturb(scene, config, seed=3), cams)
    for a, b in ((pair.corrupted.rgb, corrupted.rgb), (pair.corrupted.depth, corrupted.depth),
                 (pair.corrupted.alpha, corrupted.alpha)):
        assert a.tobytes() == b.tobytes()
    assert pair.clean.rgb.tobytes() == morphgs.render(scene, cams).rgb.tobytes()


def test_pair_seed_is_deterministic_and_changes_only_the_corrupted_side(scene, cams) -> None:
    a = morphgs.render_pair(scene, cams, config="naive", seed=3)
    b = morphgs.render_pair(scene, cams, config="naive", seed=3)
    c = morphgs.render_pair(scene, cams, config="naive", seed=4)
    np.testing.assert_array_equal(a.corrupted.rgb, b.corrupted.rgb)
    np.testing.assert_array_equal(a.clean.rgb, c.clean.rgb)
    assert not np.array_equal(a.corrupted.rgb, c.corrupted.rgb)


def test_blur2d_corrupts_by_blurring_the_clean_frames(scene, cams) -> None:
    pair = morphgs.render_pair(scene, cams, config="blur2d", blur_sigma=1.5)
    np.testing.assert_array_equal(pair.corrupted.rgb, morphgs.gaussian_blur(pair.clean.rgb, 1.5))
    np.testing.assert_array_equal(pair.corrupted.depth, pair.clean.depth)
    assert pair.config == {"kind": "blur2d", "sigma": 1.5}


def test_pair_accepts_a_path_a_config_object_and_a_camera_list(tmp_path: Path, scene, cams) -> None:
    path = tmp_path / "s.ply"
    morphgs.save_ply(scene, path)
    cfg = morphgs.PerturbConfig.preset("spatial").scaled(2.0)
    pair = morphgs.render_pair(path, list(cams), config=cfg, seed=1)
    ref = morphgs.render_pair(morphgs.load(path), cams, config=cfg.to_dict(), seed=1)
    np.testing.assert_array_equal(pair.corrupted.rgb, ref.corrupted.rgb)
    assert set(pair.timings) == {"load", "perturb", "render"}
    pair.save(tmp_path / "out")
    assert (tmp_path / "out" / "clean" / "00002.png").is_file()
    assert (tmp_path / "out" / "corrupted" / "00000.depth.exr").is_file()


def test_pair_rejects_bad_configs(scene, cams) -> None:
    with pytest.raises(ValueError, match="preset"):
        morphgs.render_pair(scene, cams, config="nonsense")
    with pytest.raises(ValueError, match="sigma"):
        morphgs.render_pair(scene, cams, config={"kind": "blur2d", "sigma": -1})
    with pytest.raises(TypeError):
        morphgs.render_pair(scene, cams, config=3)


def test_pair_of_a_shared_fixture_along_a_scene_orbit(fixtures_dir: Path) -> None:
    path = fixtures_dir / "splatapult_test.ply"  # see fixtures ATTRIBUTION.md
    s = morphgs.load(path)
    cams = trajectory.for_scene(s, 2, resolution=(40, 30))
    pair = morphgs.render_pair(path, cams, config="radiometric", seed=2)
    assert pair.clean.alpha.max() > 0.1  # the framing sees the content
