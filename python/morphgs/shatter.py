"""The `shatter` op (docs/artifacts.md): what a fit from a few views is made of.

A 3DGS fit from K views starts from points spread along the training rays and can only learn what
those views see: it reproduces each training pixel with whatever Gaussians lie on its ray, at
whatever depth they started. Seen from a training view the result is right; seen from between
them, the surfaces break into confetti of small splats at the wrong depths, coloured like the
pixels they were fitted to (docs/artifacts.md shows a built-in room fitted from 5 of 96 views).

`shatter` builds that directly, without a fit. At value v (strength x base):

- each Gaussian of the scene is removed with probability p = 1 - exp(-v);
- each pixel of each virtual training view (alpha > 0.5 in its clean render) spawns, with
  probability q = min(p, BUDGET x the removals / (PER_PIXEL x the valid pixels)), PER_PIXEL (3)
  fragments: small isotropic Gaussians on that pixel's ray (each at a uniform point within the
  pixel) at depth d' = d exp(sigma z), z ~ N(0, 1), sigma = DEPTH_SPREAD v (0.3 v), clipped to
  [d / 4, 4 d], where d is the clean render's depth there; a log-normal footprint of median
  FOOTPRINT_PX (0.5) pixel in that view; opacities that stack to the pixel's alpha;
- each fragment's colour is view-dependent (SH up to band 1), fitted by least squares to its
  own pixel (weight 4) and to the pixel of every other training view whose frustum holds it, as a
  fit makes its splats match every training view they can (a ridge of 1.0 keeps band 1 small
  where the views disagree);
- where that cannot work (a colour error above MAX_ERROR, 0.08 RMS, about 20/255, in one of those
  views, or a splat another training view would see wider than MAX_FOOTPRINT_PX, 3 pixels,
  sigma), the fragment is dropped (DROP; a fit makes what it cannot reconcile transparent), or,
  with DROP off, put back onto the surface with its pixel's colour; RETRIES other depths may be
  tried first (0 by default).

The constants were set from a real sparse:20 fit of a built-in room (docs/artifacts.md, "What a
sparse fit is made of"; `benches/sparse_anatomy.py`): with them the pairs' error spectrum is
within 0.6 dB of the real pairs' in every band. At small v a few Gaussians are replaced by
fragments close to the surface; as v grows, every Gaussian goes and the fragments spread along
their rays, as a sparse fit's do. What still differs: a real fit's training views are right
(48-51 dB), shatter's are not (12-17 dB). The op is seeded (NumPy's PCG64 keyed by (seed, 16))
and pure NumPy: the same bytes for any thread count.
"""

from __future__ import annotations

import numpy as np

__all__ = ["OP_ID", "fragments", "removal"]

#: The op's id in the seed (after the Rust kernel's 10-14 and popping's 15).
OP_ID = 16
#: Fragments per spawning pixel. A sparse fit of the built-in room from 5 of 96 views (sparse:20,
#: 3000 steps, docs/artifacts.md) holds 2.6 Gaussians per training pixel.
PER_PIXEL = 3
#: Log-depth spread per unit of value: at v = 2, sigma = 0.6, the spread of that fit's Gaussians
#: about the true surface along their nearest training ray (log depth ratio IQR -0.34..0.44,
#: 5-95 % -1.22..1.21; only 15 % within 10 % of the surface).
DEPTH_SPREAD = 0.3
#: Fragments stay within a factor DEPTH_CLIP of the surface depth (that fit: 5-95 % within a
#: factor 3.4).
DEPTH_CLIP = 4.0
#: Footprint in the spawning view: a log-normal sigma of median 0.67 pixel (that fit: median 0.67,
#: 5-95 % 0.26..1.55 pixel).
FOOTPRINT_PX = 0.5
FOOTPRINT_SPREAD = 0.5
#: The largest footprint sigma (pixels) a fragment may have in another training view that sees it.
MAX_FOOTPRINT_PX = 3.0
#: The largest colour error (RMS over the channels) a fragment may have in a training view that sees it.
MAX_ERROR = 0.08
#: Other wrong depths tried for a fragment the other training views cannot agree with.
RETRIES = 0
#: A fragment that fits no wrong depth is dropped (True) or goes back onto the surface (False).
DROP = True
#: At most this many fragments per removed Gaussian (large training views spawn at fewer pixels).
BUDGET = 4
_C0 = 0.28209479177387814


def removal(n: int, value: float, seed: int) -> np.ndarray:
    """Which of n Gaussians `shatter` removes at `value` (bool (n,)): the same uniforms at every
    value, so a larger value removes a superset."""
    u = np.random.default_rng([seed, OP_ID, 0]).random(n)
    return u < 1.0 - np.exp(-float(value))  # type: ignore[no-any-return]


def fragments(value: float, images: np.ndarray, depth: np.ndarray, alpha: np.ndarray, world_to_camera: np.ndarray,
              K: np.ndarray, removed: int, seed: int, ridge: float = 1.0,
              max_error: float | None = None) -> dict[str, np.ndarray]:
    """The fragments of the training views (module doc) as arrays of a GaussianScene (means,
    quats, log_scales, opacity_logits, sh0, and sh1: the band-1 SH coefficients (N, 3, 3)), float32,
    and view: the training view each was spawned from (N,) int32.

    Args:
        value: the op's value v > 0. images (T, H, W, 3), depth (T, H, W), alpha (T, H, W): the
            clean renders of the T training views. world_to_camera (T, 4, 4), K (T, 3, 3).
        removed: how many Gaussians were removed (the fragment budget is twice that).
    """
    max_error = MAX_ERROR if max_error is None else max_error
    t_n, h, w = depth.shape
    p = 1.0 - float(np.exp(-value))
    valid = (alpha > 0.5) & np.isfinite(depth) & (depth > 0)
    n_valid = int(valid.sum())
    if n_valid == 0 or p <= 0.0:
        return _empty()
    # pixels that spawn: a share p of them, within a budget of BUDGET fragments per removed Gaussian
    q = min(p, BUDGET * max(removed, 1) / (PER_PIXEL * n_valid))
    sigma = DEPTH_SPREAD * float(value)
    rng = np.random.default_rng([seed, OP_ID, 1])
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("means", "log_scales", "opacity_logits", "sh0", "sh1", "view")}
    for t in range(t_n):
        # the same draws per view whatever q is: a larger value spawns at a superset of pixels
        u_spawn = rng.random((h, w))
        jitter = rng.random((PER_PIXEL, h, w, 2))
        z = rng.standard_normal((RETRIES + 1, PER_PIXEL, h, w))
        size = rng.standard_normal((PER_PIXEL, h, w))
        pick = valid[t] & (u_spawn < q)
        ys, xs = np.nonzero(pick)
        if len(ys) == 0:
            continue
        k = np.repeat(np.arange(PER_PIXEL), len(ys))
        ys, xs = np.tile(ys, PER_PIXEL), np.tile(xs, PER_PIXEL)
        d = depth[t][ys, xs].astype(np.float64)
        fx, fy, cx, cy = K[t][0, 0], K[t][1, 1], K[t][0, 2], K[t][1, 2]
        px = xs + jitter[k, ys, xs, 0]
        py = ys + jitter[k, ys, xs, 1]
        m = np.asarray(world_to_camera[t], np.float64)
        r, tr = m[:3, :3], m[:3, 3]
        sigma_px = FOOTPRINT_PX * np.exp(FOOTPRINT_SPREAD * size[k, ys, xs])
        own = images[t][ys, xs].astype(np.float64)

        def place(dd: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            cam = np.stack([(px[sel] - cx) / fx * dd, (py[sel] - cy) / fy * dd, dd], axis=1)
            return (cam - tr) @ r, sigma_px[sel] * dd / (0.5 * (fx + fy))  # R^T (x - t), row-wise

        every = np.arange(len(ys))
        d2 = np.clip(d * np.exp(sigma * z[0, k, ys, xs]), d / DEPTH_CLIP, d * DEPTH_CLIP)
        world, radius = place(d2, every)
        sh0, sh1, worst, spread = _fit_colours(world, radius, own, t, images, depth, world_to_camera, K, ridge=ridge)
        # a wrong depth the other training views cannot agree with (a colour it cannot match,
        # or a splat smeared over another view) is not where a fit leaves a splat: another depth
        # is tried (RETRIES times); what still fails is dropped (DROP) or goes onto the surface
        wrong = (worst > max_error) | (spread > MAX_FOOTPRINT_PX)
        for attempt in range(1, RETRIES + 1):
            sel = np.flatnonzero(wrong)
            if len(sel) == 0:
                break
            d2[sel] = np.clip(d[sel] * np.exp(sigma * z[attempt, k[sel], ys[sel], xs[sel]]), d[sel] / DEPTH_CLIP,
                              d[sel] * DEPTH_CLIP)
            world[sel], radius[sel] = place(d2[sel], sel)
            f0, f1, fw, fs = _fit_colours(world[sel], radius[sel], own[sel], t, images, depth, world_to_camera, K,
                                          ridge=ridge)
            sh0[sel], sh1[sel] = f0, f1
            wrong[sel] = (fw > max_error) | (fs > MAX_FOOTPRINT_PX)
        if DROP and wrong.any():
            ok = ~wrong
            world, sh0, sh1, ys, xs, radius = world[ok], sh0[ok], sh1[ok], ys[ok], xs[ok], radius[ok]
        elif wrong.any():
            world[wrong], radius[wrong] = place(d[wrong], np.flatnonzero(wrong))
            sh0[wrong] = (own[wrong] - 0.5) / _C0
            sh1[wrong] = 0.0
        # opacity: the fragments over a pixel (PER_PIXEL q of them, each covering about
        # 2 pi sigma_px^2 pixels) stack up to its alpha
        cover = max(PER_PIXEL * q * 2.0 * np.pi * FOOTPRINT_PX**2, 1.0)
        target = np.clip(0.98 * alpha[t][ys, xs].astype(np.float64), 1e-4, 0.999)
        a = np.clip(1.0 - (1.0 - target) ** (1.0 / cover), 1e-3, 0.99)
        out["means"].append(world)
        out["view"].append(np.full(len(world), t))
        out["log_scales"].append(np.repeat(np.log(radius)[:, None], 3, axis=1))
        out["opacity_logits"].append(np.log(a / (1.0 - a)))
        out["sh0"].append(sh0)
        out["sh1"].append(sh1)
    if not out["means"]:
        return _empty()
    res = {k: np.ascontiguousarray(np.concatenate(v), dtype=np.float32) for k, v in out.items() if k != "view"}
    res["view"] = np.concatenate(out["view"]).astype(np.int32)
    quats = np.zeros((len(res["means"]), 4), np.float32)
    quats[:, 0] = 1.0
    res["quats"] = quats
    return res


_C1 = 0.4886025119029199


def _basis(points: np.ndarray, world_to_camera: np.ndarray) -> np.ndarray:
    """(N, 4) SH basis up to band 1 (3DGS's convention) of the directions from a camera to the points."""
    m = np.asarray(world_to_camera, np.float64)
    centre = -m[:3, :3].T @ m[:3, 3]
    d = points - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.stack([np.full(len(d), _C0), -_C1 * d[:, 1], _C1 * d[:, 2], -_C1 * d[:, 0]], axis=1)


def _fit_colours(points: np.ndarray, radius: np.ndarray, own: np.ndarray, own_view: int, images: np.ndarray, depth: np.ndarray,
                 world_to_camera: np.ndarray, K: np.ndarray, *, ridge: float,
                 slack: float = 0.02, see_through: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each fragment's SH up to band 1, least squares (band 1 ridge-regularised) over the training
    views that see it: its own (weight 4, its pixel's colour) and every other view that sees it in
    front of its clean surface or against its empty background (that view's pixel there), as a
    fit matches every training view it can. Returns (sh0 (N, 3), sh1 (N, 3, 3), the largest
    colour error (RMS over the channels) over those views (N,), the largest footprint sigma in
    pixels of `radius` in the other views (N,))."""
    t_n, h, w = depth.shape
    n = len(points)
    own_basis = _basis(points, world_to_camera[own_view])
    # who sees each fragment: (indices, basis, target colour - 0.5) per other view
    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    spread = np.zeros(n)
    for t in range(t_n):
        if t == own_view:
            continue
        m = np.asarray(world_to_camera[t], np.float64)
        c = points @ m[:3, :3].T + m[:3, 3]
        z = c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[t][0, 0] * c[:, 0] / z + K[t][0, 2]
            v = K[t][1, 1] * c[:, 1] / z + K[t][1, 2]
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx = np.flatnonzero(inside)
        ui, vi = u[idx].astype(np.int64), v[idx].astype(np.int64)
        surf = depth[t][vi, ui]
        front = np.ones(len(idx), bool) if see_through else (~np.isfinite(surf) | (surf <= 0) | (z[idx] < surf * (1.0 - slack)))
        idx, ui, vi = idx[front], ui[front], vi[front]
        if len(idx):
            spread[idx] = np.maximum(spread[idx], radius[idx] * 0.5 * (K[t][0, 0] + K[t][1, 1]) / z[idx])
            seen.append((idx, _basis(points[idx], m), images[t][vi, ui].astype(np.float64) - 0.5))
    ata = 4.0 * own_basis[:, :, None] * own_basis[:, None, :]
    atb = 4.0 * own_basis[:, :, None] * (own - 0.5)[:, None, :]
    for idx, b, target in seen:
        ata[idx] += b[:, :, None] * b[:, None, :]
        atb[idx] += b[:, :, None] * target[:, None, :]
    reg = np.diag([1e-9, ridge, ridge, ridge])
    x = np.linalg.solve(ata + reg, atb)  # (N, 4, 3)
    # the largest colour error (RMS over the channels) over the views it is fitted to
    worst = np.sqrt(np.mean((np.einsum("nk,nkc->nc", own_basis, x) - (own - 0.5)) ** 2, axis=1))
    for idx, b, target in seen:
        err = np.sqrt(np.mean((np.einsum("nk,nkc->nc", b, x[idx]) - target) ** 2, axis=1))
        worst[idx] = np.maximum(worst[idx], err)
    return x[:, 0, :], np.ascontiguousarray(x[:, 1:, :]), worst, spread


def _empty() -> dict[str, np.ndarray]:
    return {"means": np.zeros((0, 3), np.float32), "quats": np.zeros((0, 4), np.float32),
            "log_scales": np.zeros((0, 3), np.float32), "opacity_logits": np.zeros(0, np.float32),
            "sh0": np.zeros((0, 3), np.float32), "sh1": np.zeros((0, 3, 3), np.float32),
            "view": np.zeros(0, np.int32)}
