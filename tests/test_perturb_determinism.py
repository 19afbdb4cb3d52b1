"""The determinism contract of SPEC §2: bit-identical for any thread count, Gaussian i's noise in
an op independent of the other ops, the input untouched, the mask mapping results back."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import morphgs
from morphgs import PerturbConfig

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest")
OFF = dict.fromkeys(
    ("position_jitter", "color_noise", "opacity_noise", "prune", "scale_noise", "rotation_noise")
)


def make_scene(n: int = 30_000, seed: int = 0) -> morphgs.GaussianScene:
    rng = np.random.default_rng(seed)
    return morphgs.GaussianScene.from_arrays(
        means=rng.normal(size=(n, 3)) * 3,
        quats=rng.normal(size=(n, 4)),
        log_scales=rng.normal(size=(n, 3)) - 4,
        opacity_logits=rng.normal(size=n) * 2,
        sh0=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(size=(n, 8, 3)),
        extras={"filter_3D": np.arange(n, dtype=np.float32)},
    )


_CHILD = """
import hashlib, sys
import numpy as np
sys.path.insert(0, {tests!r})
import morphgs
from test_perturb_determinism import make_scene
s = make_scene(70_001)
h = hashlib.sha256()
for preset in ("naive", "radiometric", "spatial"):
    out, mask = morphgs.perturb(s, preset, seed=123, return_mask=True)
    for f in {fields!r}:
        h.update(np.ascontiguousarray(getattr(out, f)).tobytes())
    h.update(out.extras["filter_3D"].tobytes())
    h.update(mask.tobytes())
print(morphgs.num_threads(), h.hexdigest())
"""


def test_output_is_bit_identical_for_1_2_and_8_threads() -> None:
    code = _CHILD.format(tests=os.path.dirname(__file__), fields=FIELDS)
    digests = {}
    for threads in (1, 2, 8):
        env = {**os.environ, "RAYON_NUM_THREADS": str(threads)}
        env.pop("MORPHGS_NUM_THREADS", None)
        res = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        )
        used, digest = res.stdout.split()
        assert int(used) == threads
        digests[threads] = digest
    assert len(set(digests.values())) == 1, digests


def test_same_seed_same_bits_and_different_seed_different_bits() -> None:
    s = make_scene()
    a = morphgs.perturb(s, "naive", seed=9)
    b = morphgs.perturb(s, "naive", seed=9)
    c = morphgs.perturb(s, "naive", seed=10)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert not np.array_equal(a.sh0[:100], c.sh0[:100])


@pytest.mark.parametrize(
    ("op", "field"),
    [
        ("position_jitter", "means"),
        ("color_noise", "sh0"),
        ("opacity_noise", "opacity_logits"),
        ("scale_noise", "log_scales"),
        ("rotation_noise", "quats"),
    ],
)
def test_gaussian_noise_in_an_op_does_not_depend_on_the_other_ops(op: str, field: str) -> None:
    s = make_scene()
    alone = morphgs.perturb(s, PerturbConfig(**{**OFF, op: 0.05}), seed=77)
    naive = PerturbConfig(**{**PerturbConfig().to_dict(), op: 0.05})
    every, mask = morphgs.perturb(s, naive, seed=77, return_mask=True)
    np.testing.assert_array_equal(getattr(every, field), getattr(alone, field)[mask])


def test_pruning_mask_does_not_depend_on_the_other_ops() -> None:
    s = make_scene()
    _, m1 = morphgs.perturb(s, PerturbConfig(**{**OFF, "prune": 0.4}), seed=5, return_mask=True)
    _, m2 = morphgs.perturb(s, PerturbConfig(prune=0.4), seed=5, return_mask=True)
    np.testing.assert_array_equal(m1, m2)
    # a higher probability removes a superset (the same uniform draw per Gaussian)
    _, m3 = morphgs.perturb(s, PerturbConfig(**{**OFF, "prune": 0.6}), seed=5, return_mask=True)
    assert not np.any(m3 & ~m1)


def test_noise_of_gaussian_i_does_not_depend_on_the_gaussians_before_it() -> None:
    s = make_scene()
    tail = s.subset(np.arange(1000, len(s)))
    cfg = PerturbConfig(**{**OFF, "color_noise": 0.05})
    full = morphgs.perturb(s, cfg, seed=3)
    part = morphgs.perturb(tail, cfg, seed=3)
    # the tail's Gaussian 0 was Gaussian 1000: different index, different noise ...
    assert not np.array_equal(full.sh0[1000:1100], part.sh0[:100])
    # ... while a prefix keeps every index, hence every draw
    head = morphgs.perturb(s.subset(np.arange(5000)), cfg, seed=3)
    np.testing.assert_array_equal(head.sh0, full.sh0[:5000])


def test_input_scene_is_untouched() -> None:
    s = make_scene()
    before = {f: np.array(getattr(s, f), copy=True) for f in FIELDS}
    extras = np.array(s.extras["filter_3D"], copy=True)
    morphgs.perturb(s, "naive", seed=1)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(s, f), before[f])
    np.testing.assert_array_equal(s.extras["filter_3D"], extras)


def test_mask_maps_perturbed_gaussians_back_to_the_originals() -> None:
    s = make_scene()
    out, mask = morphgs.perturb(s, "morphological", seed=8, return_mask=True)
    assert 0 < len(out) < len(s)
    np.testing.assert_array_equal(out.means, s.means[mask])
    np.testing.assert_array_equal(out.sh_rest, s.sh_rest[mask])
    np.testing.assert_array_equal(out.extras["filter_3D"], np.flatnonzero(mask))
    np.testing.assert_array_equal(out.opacity_logits, s.opacity_logits[mask])


def test_without_pruning_unchanged_arrays_are_shared_not_copied() -> None:
    s = make_scene()
    out = morphgs.perturb(s, "spatial", seed=2)
    for f in ("quats", "log_scales", "opacity_logits", "sh0", "sh_rest"):
        assert np.shares_memory(getattr(out, f), getattr(s, f)), f
        assert not getattr(out, f).flags.writeable
    assert np.shares_memory(out.extras["filter_3D"], s.extras["filter_3D"])
    assert not np.shares_memory(out.means, s.means)
    assert not np.array_equal(out.means, s.means)
    pruned = morphgs.perturb(s, "morphological", seed=2)
    assert not np.shares_memory(pruned.sh_rest, s.sh_rest)


def test_config_with_every_op_disabled_is_the_identity() -> None:
    s = make_scene(5000)
    for cfg in (PerturbConfig(**OFF), PerturbConfig.preset("naive").scaled(0)):
        out = morphgs.perturb(s, cfg, seed=1)
        for f in FIELDS:
            np.testing.assert_array_equal(getattr(out, f), getattr(s, f))


def test_empty_and_degree_zero_scenes() -> None:
    empty = make_scene(0)
    out, mask = morphgs.perturb(empty, "naive", seed=1, return_mask=True)
    assert len(out) == 0 and mask.shape == (0,)
    rng = np.random.default_rng(0)
    s0 = morphgs.GaussianScene.from_arrays(
        means=rng.normal(size=(10, 3)), quats=rng.normal(size=(10, 4)),
        log_scales=np.zeros((10, 3)), opacity_logits=np.zeros(10), sh0=np.zeros((10, 3)),
    )
    out0 = morphgs.perturb(s0, "naive", seed=1)
    assert out0.sh_degree == 0 and out0.sh_rest.shape == (len(out0), 0, 3)
