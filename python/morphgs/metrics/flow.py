"""Temporal consistency: E_flow (flow end-point error), the warping error, and exact geometric flow.

Definitions (docs/metrics.md states them with the choices behind them):

- **Flow.** `F_t` is the forward optical flow from frame t to frame t+1 (pixels, (dx, dy), x right,
  y down): a pixel p of frame t moves to p + F_t(p). Estimated flow is OpenCV's DIS (Kroeger et
  al. 2016, preset "medium") on the frames' luma (uint8), deterministic and weight-free.
- **E_flow** (flow end-point error) of an output video O against its ground truth G:
  E_flow = mean over t = 0..F-2 of mean over pixels p of || F_t^O(p) - F_t^G(p) ||_2,
  where the reference flow F^G is DIS on G, or any given flow (the exact geometric flow of a
  render). With a validity mask (geometric flow) or `mask`, the pixel mean is over valid pixels.
- **Warping error** (Lai et al. 2018, `evaluate_WarpError.py`): warp O_{t+1} back onto frame t
  with the reference flow, W_t(p) = O_{t+1}(p + F_t(p)) (bilinear, edge-clamped), and average
  the squared difference over the non-occluded pixels and the channels:
  E_warp = mean over t of  sum_p M_t(p) sum_c (W_t(p)_c - O_t(p)_c)^2 / (C sum_p M_t(p)),
  images in [0, 1]. M_t excludes occlusions found by the forward-backward check of Lai et al.
  (Sundaram et al. 2010: |F_t + B_t(p + F_t)|^2 > 0.01 (|F_t|^2 + |B_t(p + F_t)|^2) + 0.5, plus
  their motion-boundary test) and, unlike their code, pixels whose target leaves the frame.
- **Geometric flow** of a render: back-project pixel centre p of frame t with its depth
  (camera z) and frame t's camera, project into frame t+1's camera; F_t(p) = p' - p. Valid where
  the depth is positive, the point is in front of camera t+1, lands inside the frame, and (given
  frame t+1's depth) is not hidden there: |z' - D_{t+1}(p')| <= tol z'.

Inputs are numpy clips (F, H, W, C) (uint8 means / 255) or (F, H, W) depth.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from morphgs.metrics import _arrays as A

__all__ = [
    "PRESETS",
    "flow_epe",
    "geometric_flow",
    "geometric_flows",
    "occlusion_mask",
    "optical_flow",
    "temporal_errors",
    "warp",
    "warping_error",
]

PRESETS = ("ultrafast", "fast", "medium")


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise A.MetricError("optical flow needs OpenCV: pip install 'morphgs[metrics]'") from e
    return cv2


def _clip(frames: Any, name: str) -> np.ndarray:
    if A.is_tensor(frames):
        raise A.MetricError(f"{name}: flow metrics take numpy clips (F, H, W, C); got a torch tensor")
    a = np.asarray(frames)
    if a.ndim != 4 or a.shape[-1] not in (1, 3):
        raise A.MetricError(f"{name}: a clip is (F, H, W, 3) or (F, H, W, 1), got shape {a.shape}")
    if a.shape[0] < 2:
        raise A.MetricError(f"{name}: flow needs at least 2 frames, got {a.shape[0]}")
    if a.dtype != np.uint8 and not np.issubdtype(a.dtype, np.floating):
        raise A.MetricError(f"{name}: frames must be uint8 or floating point, got {a.dtype}")
    return a


def _luma(frame: np.ndarray) -> np.ndarray:
    """uint8 luma (Rec. 601, as OpenCV's RGB2GRAY) of one (H, W, C) frame."""
    cv2 = _cv2()
    f = frame if frame.dtype == np.uint8 else np.rint(np.clip(frame, 0.0, 1.0) * 255.0).astype(np.uint8)
    if f.shape[-1] == 1:
        return np.ascontiguousarray(f[..., 0])
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY))


def _dis(preset: str) -> Any:
    cv2 = _cv2()
    if preset not in PRESETS:
        raise A.MetricError(f"flow preset must be one of {PRESETS}, got {preset!r}")
    return cv2.DISOpticalFlow.create(getattr(cv2, f"DISOPTICAL_FLOW_PRESET_{preset.upper()}"))


def optical_flow(frames: Any, *, backward: bool = False, preset: str = "medium") -> np.ndarray:
    """DIS optical flow between consecutive frames.

    Args:
        frames: a clip (F, H, W, C), uint8 or float in [0, 1].
        backward: False: F_t from frame t to t+1; True: B_t from frame t+1 to t.
        preset: DIS preset, "ultrafast", "fast" or "medium".

    Returns:
        (F-1, H, W, 2) float32 flows in pixels (dx, dy).

    Raises:
        MetricError: not a clip of at least 2 frames, or an unknown preset.
    """
    clip = _clip(frames, "optical_flow")
    dis = _dis(preset)
    gray = [_luma(f) for f in clip]
    out = np.empty(clip.shape[:3] + (2,), np.float32)[1:]
    for t in range(len(gray) - 1):
        a, b = (gray[t + 1], gray[t]) if backward else (gray[t], gray[t + 1])
        out[t] = dis.calc(a, b, None)
    return out


def warp(image: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Backward warp: out(p) = image(p + flow(p)), bilinear, edge-clamped.

    Returns:
        (warped image like `image` as float32, inside (H, W) bool: p + flow(p) within the frame).
    """
    cv2 = _cv2()
    h, w = flow.shape[:2]
    xs = np.arange(w, dtype=np.float32)[None, :] + flow[..., 0]
    ys = np.arange(h, dtype=np.float32)[:, None] + flow[..., 1]
    src = np.ascontiguousarray(image, dtype=np.float32)
    out = cv2.remap(src, xs, ys, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(image.shape)
    inside = (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
    return out, inside


def occlusion_mask(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """Pixels of frame t that are occluded or on a motion boundary (Lai et al. 2018's
    `detect_occlusion`): forward-backward inconsistency or a large flow gradient.

    Args:
        forward: F_t (H, W, 2), frame t -> t+1.
        backward: B_t (H, W, 2), frame t+1 -> t.

    Returns:
        (H, W) bool, True where occluded.
    """
    bw_at, _ = warp(backward, forward)                    # B_t(p + F_t(p)), on frame t's grid
    fb = forward + bw_at
    mag = lambda f: f[..., 0] ** 2 + f[..., 1] ** 2  # noqa: E731
    inconsistent = mag(fb) > 0.01 * (mag(forward) + mag(bw_at)) + 0.5
    du = np.zeros_like(forward)
    dv = np.zeros_like(forward)
    du[:, :-1] = forward[:, :-1] - forward[:, 1:]
    dv[:-1] = forward[:-1] - forward[1:]
    boundary = (du**2 + dv**2).sum(axis=-1) > 0.01 * mag(forward) + 0.002
    return np.asarray(inconsistent | boundary)


def flow_epe(
    pred: Any,
    target: Any,
    *,
    target_flow: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    mask: Any = None,
    preset: str = "medium",
    reduction: str = "mean",
) -> Any:
    """E_flow: the end-point error between the flow of `pred` and that of `target` (see the module).

    Args:
        pred, target: clips (F, H, W, C) of the same shape.
        target_flow: the reference flows (F-1, H, W, 2) instead of DIS on `target` (e.g. the
            exact `geometric_flows` of a render).
        valid: (F-1, H, W) bool, the pixels where `target_flow` holds.
        mask: optional per-pixel weights of frame t for pair t, (F-1, H, W) or (H, W).
        preset: DIS preset.
        reduction: "mean" (float) or "none" ((F-1,) per consecutive pair).

    Returns:
        Mean flow end-point error in pixels.

    Raises:
        MetricError: clips of different shapes or under 2 frames, flows of the wrong shape.
    """
    A.check_reduction(reduction)
    out = temporal_errors(pred, target, flow=target_flow, valid=valid, mask=mask, preset=preset, warp_error=False)
    return A.reduce_numpy(out["eflow"], reduction)


def warping_error(
    pred: Any,
    target: Any | None = None,
    *,
    flow: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    mask: Any = None,
    preset: str = "medium",
    reduction: str = "mean",
) -> Any:
    """E_warp: how well consecutive output frames agree along the reference motion (see the module).

    Args:
        pred: the output clip (F, H, W, C).
        target: the ground-truth clip the reference flow and occlusions come from (DIS forward and
            backward flows); not needed when `flow` is given.
        flow: reference flows (F-1, H, W, 2) instead (e.g. `geometric_flows`), with `valid` their
            (F-1, H, W) non-occluded pixels (all pixels if None).
        mask: optional per-pixel weights of frame t for pair t, (F-1, H, W) or (H, W).
        preset: DIS preset.
        reduction: "mean" (float) or "none" ((F-1,) per consecutive pair).

    Returns:
        Mean squared error per channel value, images in [0, 1].

    Raises:
        MetricError: clips of different shapes, under 2 frames, or neither `target` nor `flow`.
    """
    A.check_reduction(reduction)
    out = temporal_errors(pred, target, flow=flow, valid=valid, mask=mask, preset=preset, epe=False)
    return A.reduce_numpy(out["ewarp"], reduction)


def temporal_errors(
    pred: Any,
    target: Any | None = None,
    *,
    flow: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    mask: Any = None,
    preset: str = "medium",
    epe: bool = True,
    warp_error: bool = True,
) -> dict[str, np.ndarray]:
    """E_flow and E_warp per consecutive pair in one pass that shares the reference flows.

    Flows are computed one pair at a time (a 49-frame 832x480 clip never holds all its flows).

    Args:
        pred: the output clip (F, H, W, C).
        target: the ground-truth clip (needed unless `flow` is given and `epe` is False).
        flow, valid: reference flows (F-1, H, W, 2) and their valid pixels, instead of DIS on
            `target` (whose occlusions then come from the forward-backward check).
        mask: optional per-pixel weights (F-1, H, W) or (H, W).
        preset: DIS preset.
        epe, warp_error: which errors to compute.

    Returns:
        {"eflow": (F-1,), "ewarp": (F-1,)} for the requested errors (NaN where no pixel is valid).

    Raises:
        MetricError: clips of different shapes or under 2 frames, bad flows or masks.
    """
    p = _clip(pred, "temporal_errors")
    n, hw = p.shape[0] - 1, p.shape[1:3]
    t = None
    if target is not None:
        t = _clip(target, "temporal_errors")
        if p.shape != t.shape:
            raise A.MetricError(f"pred and target shapes differ: {p.shape} vs {t.shape}")
    elif flow is None or epe:
        raise A.MetricError("pass the ground-truth clip or reference flows")
    ref = None if flow is None else _check_flow(flow, n, hw, "reference flow")
    if valid is not None:
        if ref is None:
            raise A.MetricError("valid goes with reference flows (flow=...)")
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (n,) + hw:
            raise A.MetricError(f"valid must be (F-1, H, W) = {(n,) + hw}, got {valid.shape}")
    m = None if mask is None else A.numpy_mask(mask, (n,), hw, name="temporal_errors")
    dis = _dis(preset)
    gray_p = [_luma(f) for f in p] if epe else []
    gray_t = [_luma(f) for f in t] if t is not None and ref is None else []
    out = {k: np.full(n, np.nan) for k, on in (("eflow", epe), ("ewarp", warp_error)) if on}
    for i in range(n):
        w = None if m is None else m[i]
        if ref is not None:  # given flows: trust their validity for both errors
            fw = ref[i]
            ok = None if valid is None else valid[i]
            ok_warp = ok
        else:  # DIS on the ground truth: every pixel for E_flow, non-occluded ones for E_warp
            fw = dis.calc(gray_t[i], gray_t[i + 1], None)
            ok = None
            ok_warp = ~occlusion_mask(fw, dis.calc(gray_t[i + 1], gray_t[i], None)) if warp_error else None
        if epe:
            err = np.sqrt(((dis.calc(gray_p[i], gray_p[i + 1], None) - fw).astype(np.float64) ** 2).sum(axis=-1))
            out["eflow"][i] = _weighted_mean(err, _combine(ok, w))
        if warp_error:
            warped, inside = warp(A.as_float(p[i + 1], np.float32), fw)
            d = warped.astype(np.float64) - A.as_float(p[i])
            keep = inside if ok_warp is None else inside & ok_warp
            out["ewarp"][i] = _weighted_mean((d * d).mean(axis=-1), _combine(keep, w))
    return out


def _check_flow(flow: np.ndarray, n: int, hw: tuple[int, int], name: str) -> np.ndarray:
    f = np.asarray(flow, dtype=np.float32)
    if f.shape != (n,) + hw + (2,):
        raise A.MetricError(f"{name} must be (F-1, H, W, 2) = {(n,) + hw + (2,)}, got {f.shape}")
    return f


def _combine(ok: np.ndarray | None, w: np.ndarray | None) -> np.ndarray | None:
    if ok is None:
        return w
    return ok.astype(np.float64) if w is None else w * ok


def _weighted_mean(err: np.ndarray, w: np.ndarray | None) -> float:
    if w is None:
        return float(err.mean())
    total = float(w.sum())
    return float(np.einsum("hw,hw->", err, w) / total) if total > 0 else float("nan")


def geometric_flow(
    depth: np.ndarray,
    camera_from: Any,
    camera_to: Any,
    *,
    depth_to: np.ndarray | None = None,
    tolerance: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """The exact flow of a render between two cameras, from frame t's depth (see the module).

    Args:
        depth: (H, W) camera-z depth of frame t (0 where nothing was hit), e.g. `Render.depth`.
        camera_from, camera_to: `morphgs.Camera` of frames t and t+1 (same image size as `depth`).
        depth_to: optional (H, W) depth of frame t+1 for the visibility test.
        tolerance: relative depth tolerance of the visibility test.

    Returns:
        (flow (H, W, 2) float32, valid (H, W) bool).

    Raises:
        MetricError: a depth map whose size is not the cameras'.
    """
    d = np.asarray(depth, dtype=np.float64)
    h, w = d.shape if d.ndim == 2 else (-1, -1)
    for cam in (camera_from, camera_to):
        if d.ndim != 2 or (cam.height, cam.width) != (h, w):
            raise A.MetricError(f"geometric_flow: depth of shape {np.shape(depth)} does not match a "
                                f"{cam.width}x{cam.height} camera")
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    ok = np.isfinite(d) & (d > 0)
    z = np.where(ok, d, 0.0)
    pc = np.stack([(jj - camera_from.cx) / camera_from.fx * z, (ii - camera_from.cy) / camera_from.fy * z, z], -1)
    c2w = camera_from.camera_to_world
    rel = camera_to.world_to_camera @ c2w
    q = pc @ rel[:3, :3].T + rel[:3, 3]
    zq = q[..., 2]
    front = ok & (zq > camera_to.near)
    zs = np.where(front, zq, 1.0)
    u = camera_to.fx * q[..., 0] / zs + camera_to.cx
    v = camera_to.fy * q[..., 1] / zs + camera_to.cy
    flow = np.stack([u - jj, v - ii], -1)
    valid = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if depth_to is not None:
        dt = np.asarray(depth_to, dtype=np.float64)
        if dt.shape != (h, w):
            raise A.MetricError(f"geometric_flow: depth_to of shape {dt.shape}, expected {(h, w)}")
        iu = np.clip(np.floor(u), 0, w - 1).astype(np.intp)
        iv = np.clip(np.floor(v), 0, h - 1).astype(np.intp)
        seen = dt[iv, iu]
        valid &= np.isfinite(seen) & (np.abs(zq - seen) <= tolerance * np.abs(zq))
    return np.where(valid[..., None], flow, 0.0).astype(np.float32), valid


def geometric_flows(depths: np.ndarray, cameras: Sequence[Any], *, tolerance: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """`geometric_flow` between every pair of consecutive frames of a render.

    Args:
        depths: (F, H, W) depth maps (e.g. `Render.depth` or `morphgs.media.read_depth`).
        cameras: the F cameras (`morphgs.Cameras`).
        tolerance: relative depth tolerance of the visibility test (frame t+1's depth).

    Returns:
        (flows (F-1, H, W, 2) float32, valid (F-1, H, W) bool).

    Raises:
        MetricError: a camera count that is not the depth count, or under 2 frames.
    """
    d = np.asarray(depths)
    if d.ndim != 3 or len(d) < 2:
        raise A.MetricError(f"geometric_flows: depths must be (F, H, W) with F >= 2, got {d.shape}")
    if len(cameras) != len(d):
        raise A.MetricError(f"geometric_flows: {len(cameras)} cameras for {len(d)} depth maps")
    pairs = [geometric_flow(d[t], cameras[t], cameras[t + 1], depth_to=d[t + 1], tolerance=tolerance)
             for t in range(len(d) - 1)]
    return np.stack([f for f, _ in pairs]), np.stack([v for _, v in pairs])
