"""Gradients are the same bytes for any thread count, and for the AVX2 and AVX-512 kernels
(which perform the same operations in the same order). Each configuration runs in its own
process, since the thread count and the kernel are fixed per process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import morphgs

TESTS = Path(__file__).resolve().parent

# forward + backward of the garden frame (648x420, real cameras) and of a random SH-3 scene,
# with absgrad and a depth gradient; prints a hash of every gradient and statistic (the camera's
# viewmat gradient, a float64 sum over the Gaussians, included)
CODE = f"""
import hashlib, sys
import numpy as np
sys.path.insert(0, {str(TESTS)!r})
from backward_reference import Params, Setup, front_camera, loss_weights, random_scene, rust_backward, rust_forward
from render_reference import garden
from pathlib import Path
scene, cams = garden(Path({str(TESTS / "fixtures")!r}))
runs = [(scene, Setup(cams[1], max_alpha=0.999)),
        (random_scene(3000, 3, seed=4), Setup(front_camera(120, 90), background=(0.2, 0.4, 1.0)))]
h = hashlib.sha256()
for sc, setup in runs:
    p = Params.of(sc)
    r, images = rust_forward(p, setup)
    g = rust_backward(r, p, loss_weights(setup, seed=5))
    for a in images:
        h.update(np.ascontiguousarray(a).tobytes())
    assert "viewmat" in g
    for k in sorted(k for k in g if k != "stats"):
        h.update(k.encode())
        h.update(np.ascontiguousarray(g[k]).tobytes())
print(h.hexdigest())
"""


def digest(threads: int, simd: str = "auto") -> str:
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads), MORPHGS_SIMD=simd)
    env.pop("MORPHGS_NUM_THREADS", None)
    out = subprocess.run([sys.executable, "-c", CODE], env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


def test_gradients_are_the_same_bytes_for_1_2_and_4_threads(fixtures_dir: Path) -> None:
    one = digest(1)
    assert len(one) == 64
    assert digest(2) == one
    assert digest(4) == one


def best_kernel() -> str:
    """The blend kernel this CPU runs by default, as render reports it."""
    scene = morphgs.GaussianScene.from_arrays(
        means=[[0.0, 0.0, 0.0]], quats=[[1.0, 0.0, 0.0, 0.0]], log_scales=[[-2.0, -2.0, -2.0]],
        opacity_logits=[0.0], sh0=[[0.0, 0.0, 0.0]])
    cam = morphgs.Camera.look_at([0.0, -2.0, 0.5], [0.0, 0.0, 0.0], fov_y_degrees=50,
                                 width=8, height=8)
    return str(morphgs.render(scene, cam).stats["simd"])


def test_avx2_and_avx512_kernels_give_the_same_gradient_bytes(fixtures_dir: Path) -> None:
    if best_kernel() != "avx512":
        pytest.skip("this CPU has no AVX-512 kernel to compare with AVX2")
    assert digest(2, "avx2") == digest(2, "avx512")
    # the plain kernel rounds without FMA: different bytes (close values, tested in Rust)
    assert digest(2, "scalar") != digest(2, "avx512")
