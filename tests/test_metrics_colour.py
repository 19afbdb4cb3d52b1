"""metrics.color_shift: Delta E*ab between the mean CIELAB colours of each frame pair."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import metrics
from morphgs.color import lab_to_rgb, reinhard_transfer, rgb_to_lab


def _frames(n: int = 3, h: int = 24, w: int = 32, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.2, 0.8, size=(n, h, w, 3))  # well inside the gamut


def test_identical_frames_have_no_shift() -> None:
    x = _frames()
    assert metrics.color_shift(x, x) == 0.0
    np.testing.assert_array_equal(metrics.color_shift_components(x, x), np.zeros((3, 3)))


def test_a_known_lab_offset_is_measured() -> None:
    target = _frames(n=2)
    # move every pixel by (dL, da, db) = (1, 4, -3) in Lab: |d| = sqrt(26)
    pred = lab_to_rgb(rgb_to_lab(target) + np.array([1.0, 4.0, -3.0]))
    comp = metrics.color_shift_components(pred, target)
    np.testing.assert_allclose(comp, [[1.0, 4.0, -3.0]] * 2, atol=1e-6)
    np.testing.assert_allclose(metrics.color_shift(pred, target, reduction="none"), [np.sqrt(26.0)] * 2, rtol=1e-6)


def test_structure_does_not_count_only_colour_does() -> None:
    target = _frames(n=1, seed=1)
    shuffled = np.random.default_rng(2).permutation(target.reshape(-1, 3)).reshape(target.shape)
    assert metrics.psnr(shuffled, target) < 20.0  # a very different image...
    assert metrics.color_shift(shuffled, target) < 1e-9  # ...with the same colours
    tinted = np.clip(target * np.array([1.1, 1.0, 0.9]), 0, 1)  # a warm cast
    da, db = metrics.color_shift_components(tinted, target)[0, 1:]
    assert da > 0 and db > 0  # towards red and yellow


def test_reinhard_removes_a_constant_cast_but_not_a_growing_tint() -> None:
    target = _frames(n=4, seed=3)
    cast = np.clip(target * np.array([1.1, 1.0, 0.95]), 0, 1)
    assert metrics.color_shift(cast, target) > 3.0
    assert metrics.color_shift(reinhard_transfer(cast, target), target) < 0.5
    # a red tint that accumulates over the clip, as users report for video refiners: the
    # per-frame values show it, and one clip-wide transfer cannot undo it (it over-corrects
    # the first frames and under-corrects the last)
    tint = np.array([[1.0 + 0.05 * k, 1.0, 1.0] for k in range(4)])[:, None, None, :]
    pred = np.clip(target * tint, 0, 1)
    per_frame = metrics.color_shift(pred, target, reduction="none")
    assert per_frame[0] < 1e-9 and np.all(np.diff(per_frame) > 0.5)
    after = metrics.color_shift_components(reinhard_transfer(pred, target), target)
    assert after[0, 1] < -1.0 and after[-1, 1] > 1.0  # da*: green-ward at the start, red-ward at the end


def test_mask_weights_and_uint8_and_torch_inputs_agree() -> None:
    target = _frames(n=2, seed=4)
    pred = target.copy()
    pred[:, :, :8] = np.clip(pred[:, :, :8] + 0.2, 0, 1)  # changed only in the left 8 columns
    mask = np.ones(target.shape[:3], bool)
    mask[:, :, :8] = False
    assert metrics.color_shift(pred, target, mask=mask) < 1e-9
    assert metrics.color_shift(pred, target) > 1.0
    empty = np.zeros(target.shape[:3], bool)
    empty[0] = True
    assert np.isnan(metrics.color_shift(pred, target, mask=empty, reduction="none")[1])
    u8p, u8t = (np.rint(pred * 255).astype(np.uint8), np.rint(target * 255).astype(np.uint8))
    assert metrics.color_shift(u8p, u8t) == pytest.approx(metrics.color_shift(u8p / 255.0, u8t / 255.0), rel=1e-5)
    torch = pytest.importorskip("torch")
    tp, tt = (torch.from_numpy(a).permute(0, 3, 1, 2) for a in (pred, target))
    assert metrics.color_shift(tp, tt) == pytest.approx(metrics.color_shift(pred, target), rel=1e-6)


def test_bad_inputs_are_metric_errors() -> None:
    x = _frames()
    with pytest.raises(metrics.MetricError, match="shapes differ"):
        metrics.color_shift(x, x[:2])
    with pytest.raises(metrics.MetricError, match="3 channels"):
        metrics.color_shift(x[..., :2], x[..., :2])
    with pytest.raises(metrics.MetricError, match="reduction"):
        metrics.color_shift(x, x, reduction="sum")


def test_eval_reports_colour_shift_by_default(tmp_path: Path) -> None:
    from morphgs.evaluation import ClipPair, evaluate

    target = np.rint(_frames(n=3, h=40, w=48, seed=5) * 255).astype(np.uint8)
    pred = np.clip(target.astype(np.int16) + np.array([12, 0, -12]), 0, 255).astype(np.uint8)
    rep = evaluate([ClipPair("warm", pred, target)], metrics=("psnr", "color_shift"), out_dir=tmp_path, progress=False)
    assert rep.overall["pred"]["color_shift"] == pytest.approx(metrics.color_shift(pred, target))
    assert "color_shift" in (tmp_path / "per_frame.csv").read_text().splitlines()[0]
    assert "colour shift" in (tmp_path / "summary.md").read_text()
    assert isinstance(morphgs.__version__, str)
