"""The renderer's and the backward's output bytes are pinned: renders and gradients of the
garden fixture scene (648x420, its real cameras) and of a trained scene (PlayCanvas's guitar),
through each blend kernel, hash to the values the code gave before the culling work of issue 21
(exact ellipse-tile binning, etc.); the gradients to those since the backward's block
summation order (issue 21's fifth pass, see PINNED). Any change to which Gaussian-pixel pairs
are blended, or to the order or rounding of the arithmetic, changes a digest. Each kernel runs
in its own process (the kernel is fixed per process by MORPHGS_SIMD)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import morphgs

TESTS = Path(__file__).resolve().parent

CODE = f"""
import hashlib, json, sys
import numpy as np
sys.path.insert(0, {str(TESTS)!r})
from pathlib import Path
import morphgs
from backward_reference import Params, Setup, loss_weights, rust_backward, rust_forward
from render_reference import garden

fx = Path({str(TESTS / "fixtures")!r})
def digest(arrays):
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:32]

out = {{}}
scene, cams = garden(fx)
r = morphgs.render(scene, cams)
out["garden_3cams"] = digest([r.rgb, r.depth, r.alpha])
out["garden_evals"] = int(r.stats["evaluations"])
r = morphgs.render(scene, cams[2], max_alpha=0.999, antialiased=True, background=(0.2, 0.5, 0.9))
out["garden_aa_bg"] = digest([r.rgb, r.depth, r.alpha])
guitar = morphgs.load(fx / "playcanvas_engine_guitar.compressed.ply")
lo, hi = np.percentile(guitar.means, [2, 98], axis=0)
c = (lo + hi) / 2
d = float(np.linalg.norm(hi - lo))
gcams = [morphgs.Camera.look_at(c + d * np.array(v), c, fov_y_degrees=50, width=333, height=250)
         for v in ([0.0, -0.9, 0.3], [0.7, 0.5, 0.2])]
r = morphgs.render(guitar, gcams)
out["guitar"] = digest([r.rgb, r.depth, r.alpha])
out["guitar_evals"] = int(r.stats["evaluations"])
for name, sc, setup in [("grad_garden", scene, Setup(cams[1], max_alpha=0.999)),
                        ("grad_guitar", guitar, Setup(gcams[0], background=(0.2, 0.4, 1.0)))]:
    p = Params.of(sc)
    rr, images = rust_forward(p, setup)
    g = rust_backward(rr, p, loss_weights(setup, seed=5))
    arrays = list(images)
    for k in sorted(k for k in g if k != "stats"):
        arrays.append(np.frombuffer(k.encode(), np.uint8))
        arrays.append(g[k])
    out[name] = digest(arrays)
out["simd"] = str(r.stats["simd"])
print(json.dumps(out))
"""

# computed with the code before issue 21's changes (commit 44a414d), on an AVX-512 CPU; the
# explicit kernels' evaluation counts are those of their work units since issue 21's fourth
# pass (AVX-512: 16 per 4x4-pixel block step, AVX2: 8 per half-row step, instead of 16 per
# 16-pixel row step; same bytes). The gradient digests ("grad_*") changed once, on purpose, in
# issue 21's fifth pass (2026-11-26): the backward's per-Gaussian sums run over the lanes of
# 4x4-pixel blocks (lane (y % 4) * 4 + x % 4, its pixels in row-major order, every term summed
# per pixel) instead of tile columns, so that the AVX-512 backward walks blocks as the forward
# does; the render digests did not change.
PINNED: dict[str, dict[str, object]] = {
    "avx512": {
        "garden_3cams": "0f05d74487bd9f99b30af0b11958b8f6",
        "garden_evals": 58985248,
        "garden_aa_bg": "67c9ca1b977f8a64a56a7bfee38b2af5",
        "guitar": "42a191f4a9742e4b35643235fc296ac0",
        "guitar_evals": 10158896,
        "grad_garden": "d5e947e4f188b2b82e7cbbd5339d591e",
        "grad_guitar": "1e8fcae55ee8cd988f701e8540c8b8f8",
    },
    "avx2+fma": {
        "garden_3cams": "0f05d74487bd9f99b30af0b11958b8f6",
        "garden_evals": 57725440,
        "garden_aa_bg": "67c9ca1b977f8a64a56a7bfee38b2af5",
        "guitar": "42a191f4a9742e4b35643235fc296ac0",
        "guitar_evals": 11400120,
        "grad_garden": "d5e947e4f188b2b82e7cbbd5339d591e",
        "grad_guitar": "1e8fcae55ee8cd988f701e8540c8b8f8",
    },
    "scalar": {
        "garden_3cams": "41d983444b36a3f256a4185a28cca805",
        "garden_evals": 81046368,
        "garden_aa_bg": "1a3b01344b2895dd12ea1fd72a50160d",
        "guitar": "e40d93c94963c7c248ca3cae6ee513d9",
        "guitar_evals": 23239264,
        "grad_garden": "041a1049466e5699d367953c1e6071c2",
        "grad_guitar": "7188af2223760cef74a4fe0a8ae8db7f",
    },
}


def digests(simd: str, threads: int = 2) -> dict[str, object]:
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads), MORPHGS_SIMD=simd)
    env.pop("MORPHGS_NUM_THREADS", None)
    out = subprocess.run([sys.executable, "-c", CODE], env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


def kernels() -> list[str]:
    """The kernels this CPU can run, as render names them."""
    scene = morphgs.GaussianScene.from_arrays(
        means=[[0.0, 0.0, 0.0]], quats=[[1.0, 0.0, 0.0, 0.0]], log_scales=[[-2.0, -2.0, -2.0]],
        opacity_logits=[0.0], sh0=[[0.0, 0.0, 0.0]])
    cam = morphgs.Camera.look_at([0.0, -2.0, 0.5], [0.0, 0.0, 0.0], fov_y_degrees=50,
                                 width=8, height=8)
    best = str(morphgs.render(scene, cam).stats["simd"])
    return {"avx512": ["avx512", "avx2+fma", "scalar"], "avx2+fma": ["avx2+fma", "scalar"]}.get(
        best, ["scalar"])


@pytest.mark.parametrize("simd", ["avx512", "avx2+fma", "scalar"])
def test_render_and_gradient_bytes_are_the_pinned_ones(simd: str, fixtures_dir: Path) -> None:
    if simd not in kernels():
        pytest.skip(f"this CPU has no {simd} kernel")
    got = digests(simd.split("+")[0])
    assert got["simd"] == simd
    want = PINNED[simd]
    for key, value in want.items():
        assert got[key] == value, key
