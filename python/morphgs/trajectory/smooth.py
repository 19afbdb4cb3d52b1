"""Smooth camera paths through keyframes, and splitting paths into clips."""

from __future__ import annotations

import numpy as np

from morphgs.camera import Cameras
from morphgs.trajectory._rotations import (
    make_continuous,
    matrix_to_quat,
    quat_to_matrix,
    rotation_angle,
    squad,
    squad_controls,
)

__all__ = ["camera_sequence", "clips", "smooth_path"]

_SAMPLES_PER_SEGMENT = 64


def _catmull_rom(p: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Padded control points (N+2,3) and knots (N+2,) of a centripetal Catmull-Rom spline."""
    ext = np.concatenate([[2 * p[0] - p[1]], p, [2 * p[-1] - p[-2]]])
    d = np.linalg.norm(np.diff(ext, axis=0), axis=1)
    scale = max(float(d.max()), 1e-12)
    d = np.maximum(d, 1e-6 * scale) ** alpha
    return ext, np.concatenate([[0.0], np.cumsum(d)])


def _eval_segment(ext: np.ndarray, knots: np.ndarray, i: int, u: np.ndarray) -> np.ndarray:
    """Points on segment i (between keys i and i+1) at local parameters u in [0,1] (Barry-Goldman)."""
    p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]
    t0, t1, t2, t3 = knots[i], knots[i + 1], knots[i + 2], knots[i + 3]
    t = (t1 + (t2 - t1) * u)[:, None]
    a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
    a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
    a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
    b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
    b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
    return (t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2


def smooth_path(
    keyframes: Cameras,
    n_frames: int,
    *,
    alpha: float = 0.5,
    rotation_weight: float = 0.5,
) -> Cameras:
    """A smooth path of `n_frames` cameras through the keyframes, at near-constant speed.

    Positions follow a centripetal Catmull-Rom spline through the keyframe centres (alpha = 0.5:
    no cusps or self-intersections on uneven spacing; the end tangents come from mirrored end
    points). Orientations follow Shoemake's squad through the keyframe rotations (C1, shortest
    arcs). Intrinsics are interpolated linearly per segment. The path is then re-sampled by arc
    length in the metric |dp| + lambda * |dangle|, lambda = rotation_weight * (total distance /
    total angle) (1 for paths that do not move), so frames are evenly spaced even where keyframes
    are not and turns on the spot still get frames. The first and last frames are the first and
    last keyframes.

    Args:
        keyframes: at least one camera (one gives a still path).
        n_frames: number of output cameras.
        alpha: Catmull-Rom parametrisation (0 uniform, 0.5 centripetal, 1 chordal).
        rotation_weight: weight of rotation in the speed metric (0 = positions only).

    Returns:
        Cameras with the keyframes' image size.
    """
    n = int(n_frames)
    if n != n_frames or n < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    if len(keyframes) == 0:
        raise ValueError("smooth_path needs at least one keyframe")
    c2w = keyframes.camera_to_world
    kk = keyframes.K
    if len(keyframes) == 1:
        return Cameras.from_c2w(np.repeat(c2w, n, 0), K=np.repeat(kk, n, 0),
                                width=keyframes.width, height=keyframes.height,
                                near=keyframes.near, far=keyframes.far)
    pos = c2w[:, :3, 3]
    quats = make_continuous(matrix_to_quat(c2w[:, :3, :3]))
    ctrl = squad_controls(quats)
    ext, knots = _catmull_rom(pos, alpha)
    nseg = len(pos) - 1
    u = np.linspace(0.0, 1.0, _SAMPLES_PER_SEGMENT + 1)
    seg_pts = [_eval_segment(ext, knots, i, u) for i in range(nseg)]
    seg_q = [squad(quats[i], quats[i + 1], ctrl[i], ctrl[i + 1], u) for i in range(nseg)]
    dpos = np.concatenate([np.linalg.norm(np.diff(sp, axis=0), axis=1) for sp in seg_pts])
    dang = np.concatenate([rotation_angle(sq[:-1], sq[1:]) for sq in seg_q])
    total_len, total_ang = float(dpos.sum()), float(dang.sum())
    lam = rotation_weight * total_len / total_ang if total_len > 0 and total_ang > 0 else 1.0
    cum = np.concatenate([[0.0], np.cumsum(dpos + lam * dang)])
    # global parameter g = segment + u, sampled at the dense points
    g = np.concatenate([i + u[:-1] for i in range(nseg)] + [np.array([float(nseg)])])
    if cum[-1] <= 0:
        gq = np.zeros(n)
    else:
        gq = np.interp(np.linspace(0.0, cum[-1], n), cum, g)
    seg = np.minimum(gq.astype(np.int64), nseg - 1)
    loc = gq - seg
    out_c2w = np.tile(np.eye(4), (n, 1, 1))
    out_k = np.empty((n, 3, 3))
    for j in range(n):
        i, t = int(seg[j]), float(loc[j])
        out_c2w[j, :3, 3] = _eval_segment(ext, knots, i, np.array([t]))[0]
        out_c2w[j, :3, :3] = quat_to_matrix(squad(quats[i], quats[i + 1], ctrl[i], ctrl[i + 1], t))
        out_k[j] = (1 - t) * kk[i] + t * kk[i + 1]
    return Cameras.from_c2w(out_c2w, K=out_k, width=keyframes.width, height=keyframes.height,
                            near=keyframes.near, far=keyframes.far)


def clips(cameras: Cameras, frames: int = 16, stride: int | None = None) -> list[Cameras]:
    """Split a path into clips of `frames` consecutive cameras, starting every `stride` frames.

    16 and 49 frames are the paper's clip lengths. stride defaults to `frames` (no overlap); a
    smaller stride makes overlapping clips. A tail shorter than `frames` is dropped, so a path
    shorter than one clip gives an empty list.

    Args:
        cameras: the path.
        frames: clip length.
        stride: distance between clip starts.

    Returns:
        The clips, in path order.
    """
    f = int(frames)
    s = f if stride is None else int(stride)
    if f != frames or f < 1:
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    if s < 1 or (stride is not None and s != stride):
        raise ValueError(f"stride must be a positive integer, got {stride!r}")
    return [cameras[i:i + f] for i in range(0, len(cameras) - f + 1, s)]


def camera_sequence(centers: np.ndarray) -> list[int]:
    """The order a capture was walked in: the capture's own (video) order, unless a greedy
    nearest-neighbour path through the camera centres (from the end of the capture order farthest
    from the rest) is less than 2/3 of its length, as for photos with no order (shuffled names)."""
    n = len(centers)
    if n < 3:
        return list(range(n))
    c = np.asarray(centers, np.float64)

    def length(order: list[int]) -> float:
        return float(np.linalg.norm(np.diff(c[order], axis=0), axis=1).sum())

    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    start = int(np.argmax(d.sum(axis=1)))
    order, left = [start], set(range(n)) - {start}
    while left:
        last = order[-1]
        nxt = min(left, key=lambda k: (d[last, k], k))
        order.append(nxt)
        left.remove(nxt)
    return order if length(order) < length(list(range(n))) * 2 / 3 else list(range(n))
