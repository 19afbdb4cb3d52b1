"""Point-cloud geometry: Chamfer distance and F-score (Tanks and Temples), KD-tree based.

Conventions. With d_P(p) = min over q in G of ||p - q||_2 for each predicted point p and
d_G(q) = min over p in P of ||q - p||_2 for each ground-truth point q (scipy `cKDTree`):

- accuracy = mean d_P, completeness = mean d_G (DTU's names);
- **Chamfer = (accuracy + completeness) / 2**, unsquared Euclidean distances (DTU's "overall").
  `squared=True` averages squared distances instead; PyTorch3D's `chamfer_distance` (sum of the
  two squared means) is twice that value;
- precision(tau) = fraction of P with d_P < tau, recall(tau) = fraction of G with d_G < tau,
  **F-score = 2 P R / (P + R)** (0 when both are 0), as the Tanks and Temples toolbox.

Clouds come from a Gaussian scene (`scene_points`: centres of Gaussians above an opacity) or from
depth maps (`backproject_depth`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A

__all__ = ["backproject_depth", "chamfer_distance", "fscore", "nearest_distances", "point_cloud_metrics",
           "point_cloud_metrics_at", "scene_points"]


def _cloud(points: Any, name: str) -> np.ndarray:
    if A.is_tensor(points):
        points = points.detach().cpu().numpy()
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise A.MetricError(f"{name}: a point cloud is (N, 3), got shape {a.shape}")
    if len(a) == 0:
        raise A.MetricError(f"{name}: the point cloud is empty")
    if not np.all(np.isfinite(a)):
        raise A.MetricError(f"{name}: the point cloud holds NaN or Inf coordinates")
    return a


def nearest_distances(pred: Any, target: Any) -> tuple[np.ndarray, np.ndarray]:
    """(d_P, d_G): each predicted point's distance to the nearest target point, and the reverse.

    Raises:
        MetricError: a cloud that is not a non-empty finite (N, 3) array.
    """
    from scipy.spatial import cKDTree

    p, g = _cloud(pred, "pred"), _cloud(target, "target")
    d_p, _ = cKDTree(g).query(p, k=1, workers=-1)
    d_g, _ = cKDTree(p).query(g, k=1, workers=-1)
    return np.asarray(d_p, dtype=np.float64), np.asarray(d_g, dtype=np.float64)


def chamfer_distance(pred: Any, target: Any, *, squared: bool = False) -> float:
    """Chamfer distance (accuracy + completeness) / 2 (see the module for the convention)."""
    d_p, d_g = nearest_distances(pred, target)
    if squared:
        d_p, d_g = d_p**2, d_g**2
    return float(0.5 * (d_p.mean() + d_g.mean()))


def fscore(pred: Any, target: Any, *, threshold: float) -> tuple[float, float, float]:
    """(F-score, precision, recall) at distance `threshold` (see the module).

    Raises:
        MetricError: a non-positive threshold or a bad cloud.
    """
    m = point_cloud_metrics(pred, target, threshold=threshold)
    return m["fscore"], m["precision"], m["recall"]


def point_cloud_metrics(pred: Any, target: Any, *, threshold: float) -> dict[str, float]:
    """Chamfer, accuracy, completeness, precision, recall and F-score in one KD-tree pass.

    Raises:
        MetricError: a non-positive threshold or a bad cloud.
    """
    return point_cloud_metrics_at(pred, target, thresholds=[threshold])[0]


def point_cloud_metrics_at(pred: Any, target: Any, *, thresholds: Sequence[float]) -> list[dict[str, float]]:
    """`point_cloud_metrics` at each of `thresholds`, from one KD-tree pass (the same numbers).

    Raises:
        MetricError: a non-positive threshold or a bad cloud.
    """
    for threshold in thresholds:
        if not (np.isfinite(threshold) and threshold > 0):
            raise A.MetricError(f"threshold must be a positive distance, got {threshold!r}")
    d_p, d_g = nearest_distances(pred, target)
    out = []
    for threshold in thresholds:
        precision = float(np.mean(d_p < threshold))
        recall = float(np.mean(d_g < threshold))
        f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
        out.append({"chamfer": float(0.5 * (d_p.mean() + d_g.mean())), "accuracy": float(d_p.mean()),
                    "completeness": float(d_g.mean()), "precision": precision, "recall": recall, "fscore": f})
    return out


def scene_points(scene: Any, *, min_opacity: float = 0.5) -> np.ndarray:
    """Centres (N, 3) of a `GaussianScene`'s Gaussians whose opacity sigmoid(logit) >= min_opacity."""
    if not (0.0 <= min_opacity < 1.0):
        raise A.MetricError(f"min_opacity must be in [0, 1), got {min_opacity}")
    means = np.asarray(scene.means, dtype=np.float64)
    return means[np.asarray(scene.opacities) >= min_opacity]


def backproject_depth(depth: Any, camera: Any, *, mask: Any = None) -> np.ndarray:
    """World points (N, 3) of a depth map's valid pixels (finite, > 0, and in `mask`).

    Pixel (i, j) has its centre at (j + 0.5, i + 0.5); the depth is camera z (OpenCV axes), as
    `Render.depth` and `morphgs.media.read_depth` give it.

    Raises:
        MetricError: a depth map whose size is not the camera's, or a mask of another size.
    """
    d = np.asarray(depth.detach().cpu().numpy() if A.is_tensor(depth) else depth, dtype=np.float64)
    if d.shape != (camera.height, camera.width):
        raise A.MetricError(f"backproject_depth: depth of shape {d.shape} does not match a "
                            f"{camera.width}x{camera.height} camera")
    valid = np.isfinite(d) & (d > 0)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != d.shape:
            raise A.MetricError(f"backproject_depth: mask of shape {m.shape}, expected {d.shape}")
        valid &= m
    ii, jj = np.nonzero(valid)
    z = d[ii, jj]
    pc = np.stack([(jj + 0.5 - camera.cx) / camera.fx * z, (ii + 0.5 - camera.cy) / camera.fy * z, z], 1)
    c2w = camera.camera_to_world
    return np.asarray(pc @ c2w[:3, :3].T + c2w[:3, 3])
