"""Depth errors (Eigen et al.) and point-cloud Chamfer / F-score on cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from metrics_data import GUITAR, guitar_pair

import morphgs
from morphgs import metrics
from morphgs.camera import Camera
from morphgs.metrics import MetricError


def _gt_depth() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform(1.0, 10.0, (3, 12, 16))


# ---- depth ----

def test_depth_metrics_hand_computed_for_a_uniform_scale_error() -> None:
    gt = _gt_depth()
    m = metrics.depth_metrics(1.2 * gt, gt)
    assert m["abs_rel"] == pytest.approx(0.2)
    assert m["sq_rel"] == pytest.approx(np.mean([0.04 * g.mean() for g in gt]))
    assert m["rmse"] == pytest.approx(np.mean([0.2 * np.sqrt((g**2).mean()) for g in gt]))
    assert m["rmse_log"] == pytest.approx(np.log(1.2))
    assert (m["delta1"], m["delta2"], m["delta3"]) == (1.0, 1.0, 1.0)
    far = metrics.depth_metrics(1.6 * gt, gt)                     # 1.25^2 < 1.6 < 1.25^3
    assert (far["delta1"], far["delta2"], far["delta3"]) == (0.0, 0.0, 1.0)


def test_alignment_removes_a_known_scale_and_shift() -> None:
    gt = _gt_depth()
    for align, pred in (("median", 0.37 * gt), ("lstsq", 0.37 * gt + 0.5)):
        m = metrics.depth_metrics(pred, gt, align=align)
        assert m["abs_rel"] == pytest.approx(0.0, abs=1e-9) and m["delta1"] == 1.0
    assert metrics.depth_metrics(0.37 * gt, gt)["delta1"] == 0.0   # without alignment the scale shows


def test_invalid_pixels_masks_and_reductions() -> None:
    gt = _gt_depth()
    pred = gt.copy()
    pred[0, :, :8] = 100.0                                          # wrong only where the mask excludes
    gt_holes = gt.copy()
    gt_holes[1, :6] = 0.0                                           # no ground truth there
    gt_holes[1, 6:, :2] = np.nan
    pred[1, :6] = 50.0
    mask = np.ones(gt.shape[1:], bool)
    mask[:, :8] = False
    m = metrics.depth_metrics(pred, gt_holes, mask=mask, reduction="none")
    np.testing.assert_allclose(m["abs_rel"], 0.0, atol=1e-12)
    empty = metrics.depth_metrics(pred, gt_holes, mask=np.zeros(gt.shape, bool), reduction="none")
    assert np.isnan(empty["rmse"]).all() and np.isnan(metrics.depth_metrics(pred, np.zeros_like(gt))["rmse"])
    capped = metrics.depth_metrics(pred, gt, max_depth=20.0, reduction="none")    # predictions clipped to 20
    assert capped["rmse"][0] < metrics.depth_metrics(pred, gt, reduction="none")["rmse"][0]
    t = metrics.depth_metrics(torch.from_numpy(1.2 * gt), torch.from_numpy(gt))
    assert t["abs_rel"] == pytest.approx(0.2)


def test_depth_of_a_perturbed_render_against_the_clean_one() -> None:
    pair = guitar_pair()
    seen = pair.clean.alpha > 0.5
    m = metrics.depth_metrics(pair.corrupted.depth, pair.clean.depth, mask=seen, reduction="none")
    assert m["abs_rel"].shape == (len(seen),)
    assert np.all((m["abs_rel"] > 0) & (m["abs_rel"] < 0.5)) and np.all(m["delta3"] > 0.8)
    same = metrics.depth_metrics(pair.clean.depth, pair.clean.depth, mask=seen)
    assert same["abs_rel"] == 0.0 and same["delta1"] == 1.0


def test_depth_bad_input() -> None:
    gt = _gt_depth()
    with pytest.raises(MetricError, match="shapes differ"):
        metrics.depth_metrics(gt[:2], gt)
    with pytest.raises(MetricError, match="align must be"):
        metrics.depth_metrics(gt, gt, align="mean")
    with pytest.raises(MetricError, match="min_depth < max_depth"):
        metrics.depth_metrics(gt, gt, min_depth=1.0, max_depth=0.5)


# ---- geometry ----

def _grid(n: int = 6) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 3)
    return g.astype(np.float64)


def test_chamfer_and_fscore_of_a_shifted_cloud() -> None:
    gt = _grid()
    pred = gt + [0.01, 0.0, 0.0]                                    # every nearest distance is 0.01
    assert metrics.chamfer_distance(pred, gt) == pytest.approx(0.01)
    assert metrics.chamfer_distance(pred, gt, squared=True) == pytest.approx(1e-4)
    assert metrics.fscore(pred, gt, threshold=0.02) == pytest.approx((1.0, 1.0, 1.0))
    assert metrics.fscore(pred, gt, threshold=0.005) == (0.0, 0.0, 0.0)


def test_missing_points_lower_recall_and_raise_completeness() -> None:
    gt = _grid()
    keep = gt[:, 0] < 3                                             # half of the grid, x in {0, 1, 2}
    m = metrics.point_cloud_metrics(gt[keep], gt, threshold=0.5)
    assert m["accuracy"] == 0.0 and m["precision"] == 1.0 and m["recall"] == pytest.approx(0.5)
    # the missing points lie 1, 2 and 3 units from the kept slab x = 2
    assert m["completeness"] == pytest.approx((0 * 3 + 1 + 2 + 3) / 6)
    assert m["chamfer"] == pytest.approx(m["completeness"] / 2)
    assert m["fscore"] == pytest.approx(2 * 0.5 / 1.5)


def test_metrics_at_several_thresholds_are_those_of_each_threshold_alone() -> None:
    rng = np.random.default_rng(2)
    gt = _grid()
    pred = gt[gt[:, 0] < 4] + rng.normal(scale=0.3, size=(int((gt[:, 0] < 4).sum()), 3))
    at = metrics.point_cloud_metrics_at(pred, gt, thresholds=[0.1, 0.3, 1.0])
    assert at == [metrics.point_cloud_metrics(pred, gt, threshold=t) for t in (0.1, 0.3, 1.0)]
    assert at[0]["fscore"] < at[1]["fscore"] < at[2]["fscore"]
    with pytest.raises(MetricError, match="threshold"):
        metrics.point_cloud_metrics_at(pred, gt, thresholds=[0.1, -1.0])


def test_nearest_distances_match_brute_force() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    d_a, d_b = metrics.nearest_distances(a, b)
    np.testing.assert_allclose(d_a, d.min(1))
    np.testing.assert_allclose(d_b, d.min(0))


def test_scene_points_and_backprojected_depth() -> None:
    scene = morphgs.load(GUITAR)
    pts = metrics.scene_points(scene, min_opacity=0.5)
    assert len(pts) == int((scene.opacities >= 0.5).sum()) and 0 < len(pts) < len(scene)
    fx, z = 20.0, 3.0
    cam = Camera.from_c2w(np.eye(4), fx=fx, width=8, height=6)
    depth = np.full((6, 8), z)
    depth[0, 0] = 0.0                                               # nothing hit: no point
    p = metrics.backproject_depth(depth, cam)
    assert p.shape == (47, 3) and np.allclose(p[:, 2], z)
    np.testing.assert_allclose(p[0], [(1.5 - 4) / fx * z, (0.5 - 3) / fx * z, z])
    np.testing.assert_allclose(cam.project(p)[0], [1.5, 0.5])       # pixel centres round-trip
    # the clean render's depth, back-projected, lies among the scene's opaque Gaussians (within
    # their extent: about 10% of the 1.7-unit viewing distance)
    pair = guitar_pair()
    cloud = metrics.backproject_depth(pair.clean.depth[0], pair.cameras[0], mask=pair.clean.alpha[0] > 0.9)
    assert metrics.point_cloud_metrics(cloud, pts, threshold=0.15)["precision"] > 0.95
    sideways = cloud + pair.cameras[0].camera_to_world[:3, 0] * 0.5  # moved 0.5 units along the camera's x
    assert metrics.point_cloud_metrics(sideways, pts, threshold=0.15)["precision"] < 0.2


def test_geometry_bad_input() -> None:
    with pytest.raises(MetricError, match="empty"):
        metrics.chamfer_distance(np.zeros((0, 3)), _grid())
    with pytest.raises(MetricError, match=r"\(N, 3\)"):
        metrics.chamfer_distance(np.zeros((4, 2)), _grid())
    with pytest.raises(MetricError, match="threshold"):
        metrics.fscore(_grid(), _grid(), threshold=0.0)
