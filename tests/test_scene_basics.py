"""GaussianScene construction, validation and the basic load path."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import morphgs


def _arrays(n: int = 5, k: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return dict(
        means=rng.normal(size=(n, 3)),
        quats=rng.normal(size=(n, 4)),
        log_scales=rng.normal(size=(n, 3)) - 3,
        opacity_logits=rng.normal(size=n),
        sh0=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(size=(n, k, 3)),
    )


def test_from_arrays_casts_to_float32_and_normalises_quats() -> None:
    a = _arrays()
    s = morphgs.GaussianScene.from_arrays(**a)
    assert len(s) == 5 and s.sh_degree == 1
    assert s.means.dtype == np.float32 and s.sh_rest.shape == (5, 3, 3)
    np.testing.assert_allclose(np.linalg.norm(s.quats, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(s.scales, np.exp(a["log_scales"]).astype(np.float32), rtol=1e-6)
    assert not s.means.flags.writeable


def test_from_arrays_rejects_bad_shapes_and_dtypes() -> None:
    a = _arrays()
    with pytest.raises(ValueError, match="quats"):
        morphgs.GaussianScene.from_arrays(**{**a, "quats": a["quats"][:, :3]})
    with pytest.raises(ValueError, match="no SH degree"):
        morphgs.GaussianScene.from_arrays(**{**a, "sh_rest": np.zeros((5, 4, 3))})
    with pytest.raises(TypeError, match="sh0"):
        morphgs.GaussianScene.from_arrays(**{**a, "sh0": np.array([["a"] * 3] * 5)})


def test_degree_zero_when_sh_rest_missing() -> None:
    a = _arrays()
    del a["sh_rest"]
    s = morphgs.GaussianScene.from_arrays(**a)
    assert s.sh_degree == 0 and s.sh_rest.shape == (5, 0, 3)


def test_subset_by_mask_and_indices_and_pickle() -> None:
    s = morphgs.GaussianScene.from_arrays(**_arrays(), extras={"filter_3D": np.arange(5)})
    m = s.subset(np.array([True, False, True, False, True]))
    np.testing.assert_array_equal(m.means, s.means[[0, 2, 4]])
    np.testing.assert_array_equal(m.extras["filter_3D"], [0, 2, 4])
    i = s.subset([4, -5])
    np.testing.assert_array_equal(i.sh_rest, s.sh_rest[[4, 0]])
    with pytest.raises(IndexError):
        s.subset([5])
    t = pickle.loads(pickle.dumps(s))
    np.testing.assert_array_equal(t.sh_rest, s.sh_rest)
    assert t.extras.keys() == s.extras.keys()


def test_missing_file_raises_file_not_found(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        morphgs.load(tmp_path / "absent.ply")


def test_fixture_ply_loads(fixtures_dir) -> None:
    s = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    assert len(s) == 3 and s.sh_degree == 3
