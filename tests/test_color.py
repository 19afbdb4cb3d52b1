"""Reinhard colour transfer in CIELAB (morphgs.color): the Lab conversion is scikit-image's, the
transfer gives the reference's statistics, and a known colour cast is undone."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.color import lab2rgb, rgb2lab

from morphgs.color import lab_stats, lab_to_rgb, reinhard_transfer, rgb_to_lab


def _clip(seed: int = 0, f: int = 5, h: int = 24, w: int = 32) -> np.ndarray:
    """A smooth, colourful clip (float in [0, 1]) that stays well inside the sRGB gamut."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    frames = [np.stack([0.3 + 0.4 * x + 0.05 * t, 0.3 + 0.4 * y, 0.5 - 0.2 * x * y], -1) for t in range(f)]
    return np.clip(np.stack(frames) + rng.normal(0, 0.02, (f, h, w, 3)), 0.05, 0.95)


def test_lab_conversion_matches_scikit_image_and_round_trips() -> None:
    x = np.random.default_rng(1).random((3, 9, 7, 3))
    # scikit-image rounds the CIE constants (0.008856, 7.787); morphgs uses the exact (6/29)^3 and
    # 1/(3 (6/29)^2), which moves values near that knee by ~1e-4
    np.testing.assert_allclose(rgb_to_lab(x), rgb2lab(x), atol=1e-3)
    lab = rgb2lab(x)
    np.testing.assert_allclose(lab_to_rgb(lab), lab2rgb(lab), atol=1e-5)
    np.testing.assert_allclose(lab_to_rgb(rgb_to_lab(x)), x, atol=1e-12)
    np.testing.assert_allclose(rgb_to_lab(np.array([1.0, 0.0, 0.0])), [53.2406, 80.0923, 67.2028], atol=1e-3)
    u8 = (x * 255).astype(np.uint8)
    np.testing.assert_allclose(rgb_to_lab(u8), rgb2lab(u8), atol=1e-3)


def test_transfer_gives_the_reference_statistics_over_the_whole_clip() -> None:
    src, ref = _clip(0), _clip(3, f=3, h=16, w=20)[..., ::-1] * 0.8 + 0.1
    out = reinhard_transfer(src, ref)
    assert out.dtype == np.float32 and out.shape == src.shape
    m_out, s_out = lab_stats(out)
    m_ref, s_ref = lab_stats(ref)
    np.testing.assert_allclose(m_out, m_ref, atol=0.05)
    np.testing.assert_allclose(s_out, s_ref, rtol=0.01, atol=0.02)
    # one transform for the whole clip: frame-to-frame differences keep their sign (no per-frame drift)
    assert np.all(np.diff(rgb_to_lab(out)[..., 0].mean(axis=(1, 2))) > 0)


def test_a_known_colour_cast_is_undone() -> None:
    clean = _clip(2)
    # a cast that is affine in Lab (yellow-green tint, lower contrast, brighter) is undone exactly
    lab = rgb_to_lab(clean)
    lab_cast = (lab - lab.mean(axis=(0, 1, 2))) * [0.8, 1.1, 0.9] + lab.mean(axis=(0, 1, 2)) + [6.0, -8.0, 12.0]
    cast = lab_to_rgb(lab_cast)
    assert cast.min() >= 0 and cast.max() <= 1  # stays in gamut, so nothing is clipped
    assert np.abs(cast - clean).mean() > 0.03
    np.testing.assert_allclose(reinhard_transfer(cast, clean), clean, atol=1e-4)
    # a per-channel RGB gain (not affine in Lab) is mostly undone
    gain = np.clip(clean * np.array([1.15, 0.95, 0.8]) + np.array([0.0, 0.02, 0.05]), 0, 1)
    before = np.abs(gain - clean).mean()
    after = np.abs(reinhard_transfer(gain, clean) - clean).mean()
    assert after < before / 3, (before, after)


def test_a_clip_is_its_own_fixed_point_and_bad_shapes_are_refused() -> None:
    x = _clip(4)
    np.testing.assert_allclose(reinhard_transfer(x, x), x, atol=1e-5)
    with pytest.raises(ValueError, match=r"got shape \(2, 4, 4, 4\)"):
        reinhard_transfer(np.zeros((2, 4, 4, 4)), x)
    with pytest.raises(ValueError, match=r"\(F, H, W, 3\)"):
        reinhard_transfer(np.zeros((0, 4, 4, 3)), x)
