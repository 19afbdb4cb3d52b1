"""The native 2D blur behind config="blur2d" (the paper's "2D Render Blur" baseline)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import morphgs


def _kernel(sigma: float) -> np.ndarray:
    r = int(np.ceil(3 * sigma))
    x = np.arange(-r, r + 1)
    w = np.exp(-(x * x) / (2 * sigma * sigma))
    return w / w.sum()


def test_blur_matches_a_float64_separable_convolution_with_replicated_edges() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((2, 13, 17, 3), dtype=np.float32)
    sigma = 1.3
    k = _kernel(sigma)
    r = len(k) // 2
    ref = img.astype(np.float64)
    pad = np.pad(ref, ((0, 0), (0, 0), (r, r), (0, 0)), mode="edge")
    ref = sum(k[i] * pad[:, :, i:i + 17] for i in range(len(k)))
    pad = np.pad(ref, ((0, 0), (r, r), (0, 0), (0, 0)), mode="edge")
    ref = sum(k[i] * pad[:, i:i + 13] for i in range(len(k)))
    out = morphgs.gaussian_blur(img, sigma)
    assert out.shape == img.shape and out.dtype == np.float32
    np.testing.assert_allclose(out, ref, atol=2e-6)


def test_blur_keeps_shape_for_single_images_and_sigma_zero_is_identity() -> None:
    img = np.random.default_rng(1).random((9, 7), dtype=np.float32)
    assert morphgs.gaussian_blur(img, 1.0).shape == (9, 7)
    np.testing.assert_array_equal(morphgs.gaussian_blur(img, 0.0), img)


@pytest.mark.parametrize("sigma", [-1.0, float("nan"), 1e6])
def test_blur_rejects_bad_sigma(sigma: float) -> None:
    with pytest.raises(ValueError, match="sigma"):
        morphgs.gaussian_blur(np.zeros((4, 4, 3), np.float32), sigma)


def test_blur_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="shape"):
        morphgs.gaussian_blur(np.zeros((2, 2, 2, 2, 2), np.float32), 1.0)


def test_blur_is_identical_for_one_and_two_threads() -> None:
    code = ("import numpy as np, morphgs, sys; x = np.random.default_rng(3).random((3, 40, 50, 3), dtype=np.float32);"
            "sys.stdout.buffer.write(morphgs.gaussian_blur(x, 2.5).tobytes())")
    outs = []
    for n in ("1", "2"):
        env = dict(os.environ, RAYON_NUM_THREADS=n, MORPHGS_NUM_THREADS=n)
        outs.append(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, check=True).stdout)
    assert outs[0] == outs[1] and len(outs[0]) == 3 * 40 * 50 * 3 * 4


def test_blur_of_a_fortran_ordered_or_strided_stack_equals_the_blur_of_its_c_copy() -> None:
    rng = np.random.default_rng(3)
    img = rng.random((2, 12, 10, 3), dtype=np.float32)
    want = morphgs.gaussian_blur(img, 1.5)
    np.testing.assert_array_equal(morphgs.gaussian_blur(np.asfortranarray(img), 1.5), want)
    wide = rng.random((2, 12, 20, 3), dtype=np.float32)
    np.testing.assert_array_equal(morphgs.gaussian_blur(wide[:, :, ::2], 1.5),
                                  morphgs.gaussian_blur(np.ascontiguousarray(wide[:, :, ::2]), 1.5))
