"""Reference renderer for the rasterizer tests and benchmarks.

Projection and SH colour come from gsplat 1.5.3's pure-PyTorch functions
(`gsplat.cuda._torch_impl`, run on CPU); the opacity-aware extent and the 1/255 cull of SPEC §4
step 4 are applied on top, as gsplat's CUDA projection does. The blend is SPEC §4 steps 6-7
written plainly in float64 with NumPy, tile by tile (gsplat's `isect_tiles` ranges).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import morphgs

ALPHA_THRESHOLD = 1.0 / 255.0
TILE = 16


@dataclass
class RefProjection:
    """Per-Gaussian projection in float64 (radii 0 where culled)."""

    radii: np.ndarray  # (N,2) int
    means2d: np.ndarray  # (N,2)
    depths: np.ndarray  # (N,)
    conics: np.ndarray  # (N,3)
    opacities: np.ndarray  # (N,)
    colors: np.ndarray  # (N,3)


def gsplat_project(
    scene: morphgs.GaussianScene,
    cam: morphgs.Camera,
    *,
    sh_degree: int | None = None,
    antialiased: bool = False,
) -> RefProjection:
    """gsplat's torch projection + SH of every Gaussian, with SPEC's opacity-aware radii."""
    import torch

    torch.set_num_threads(1)
    from gsplat.cuda._torch_impl import (
        _fully_fused_projection,
        _quat_scale_to_covar_preci,
        _spherical_harmonics,
    )

    n = len(scene)
    means = torch.from_numpy(np.array(scene.means))
    quats = torch.from_numpy(np.array(scene.quats))
    scales = torch.exp(torch.from_numpy(np.array(scene.log_scales)))
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    viewmats = torch.from_numpy(np.asarray(cam.world_to_camera, dtype=np.float32))[None]
    ks = torch.from_numpy(np.asarray(cam.K, dtype=np.float32))[None]
    radii, means2d, depths, conics, comp = _fully_fused_projection(
        means, covars, viewmats, ks, cam.width, cam.height, eps2d=0.3,
        near_plane=cam.near, far_plane=cam.far, calc_compensations=antialiased,
    )
    radii = radii[0].numpy()
    means2d = means2d[0].double().numpy()
    depths = depths[0].double().numpy()
    conics = conics[0].double().numpy()
    with np.errstate(over="ignore"):
        opac = 1.0 / (1.0 + np.exp(-np.asarray(scene.opacity_logits, dtype=np.float64)))
    if antialiased:
        assert comp is not None
        c2 = comp[0].double().numpy() ** 2
        opac = opac * np.sqrt(np.maximum(0.005**2, c2))

    degree = min(scene.sh_degree, 3) if sh_degree is None else sh_degree
    coeffs = np.concatenate([np.array(scene.sh0)[:, None, :], np.array(scene.sh_rest)], axis=1)
    nb = (degree + 1) ** 2
    center = cam.center
    dirs = torch.from_numpy(np.array(scene.means) - center.astype(np.float32))
    if n:
        rgb = _spherical_harmonics(degree, dirs, torch.from_numpy(coeffs[:, :nb].copy()))
        colors = np.maximum(rgb.double().numpy() + 0.5, 0.0)
    else:
        colors = np.zeros((0, 3))

    # SPEC step 4: opacity cull and opacity-aware extent (gsplat's CUDA kernel)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        det = conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2
        cov_xx = conics[:, 2] / det
        cov_yy = conics[:, 0] / det
        extent = np.minimum(3.33, np.sqrt(2.0 * np.log(np.maximum(opac, 1e-30) / ALPHA_THRESHOLD)))
        rx = np.ceil(extent * np.sqrt(cov_xx))
        ry = np.ceil(extent * np.sqrt(cov_yy))
        keep = (radii > 0).all(axis=1) & (opac >= ALPHA_THRESHOLD) & (rx > 0) & (ry > 0)
        keep &= np.all(np.isfinite(np.stack([rx, ry, means2d[:, 0], means2d[:, 1]], 1)), axis=1)
        keep &= (means2d[:, 0] + rx > 0) & (means2d[:, 0] - rx < cam.width)
        keep &= (means2d[:, 1] + ry > 0) & (means2d[:, 1] - ry < cam.height)
    r = np.zeros((n, 2), dtype=np.int64)
    r[keep, 0] = rx[keep]
    r[keep, 1] = ry[keep]
    return RefProjection(r, means2d, depths, conics, opac, colors)


def reference_blend(
    p: RefProjection,
    width: int,
    height: int,
    *,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    max_alpha: float = 0.99,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SPEC §4 steps 6-7 in float64. Returns rgb (H,W,3), depth (H,W), alpha (H,W)."""
    idx = np.nonzero((p.radii > 0).all(axis=1))[0]
    order = idx[np.lexsort((idx, p.depths[idx]))]  # by depth, ties by index
    m = p.means2d[order]
    r = p.radii[order].astype(np.float64)
    con = p.conics[order]
    op = p.opacities[order]
    col = p.colors[order]
    dep = p.depths[order]
    tw, th = math.ceil(width / TILE), math.ceil(height / TILE)
    tx0 = np.clip(np.floor(m[:, 0] / TILE - r[:, 0] / TILE), 0, tw).astype(np.int64)
    tx1 = np.clip(np.ceil(m[:, 0] / TILE + r[:, 0] / TILE), 0, tw).astype(np.int64)
    ty0 = np.clip(np.floor(m[:, 1] / TILE - r[:, 1] / TILE), 0, th).astype(np.int64)
    ty1 = np.clip(np.ceil(m[:, 1] / TILE + r[:, 1] / TILE), 0, th).astype(np.int64)
    # (tile, depth-order position) pairs, grouped by tile in depth order
    wid = tx1 - tx0
    counts = wid * (ty1 - ty0)
    gid = np.repeat(np.arange(len(order)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    tile = (ty0[gid] + local // np.maximum(wid[gid], 1)) * tw + tx0[gid] + local % np.maximum(wid[gid], 1)
    pairs = np.lexsort((gid, tile))
    gid, tile = gid[pairs], tile[pairs]
    bounds = np.searchsorted(tile, np.arange(tw * th + 1))
    rgb = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    alpha = np.zeros((height, width))
    bg = np.asarray(background, dtype=np.float64)
    for ty in range(th):
        for tx in range(tw):
            t = ty * tw + tx
            sel = gid[bounds[t]:bounds[t + 1]]
            x0, y0 = tx * TILE, ty * TILE
            xs = np.arange(x0, min(x0 + TILE, width))
            ys = np.arange(y0, min(y0 + TILE, height))
            px, py = np.meshgrid(xs + 0.5, ys + 0.5)
            px, py = px.ravel(), py.ravel()
            if len(sel) == 0:
                t_final = np.ones(px.shape)
                c = np.zeros((px.size, 3))
                d = np.zeros(px.size)
            else:
                dx = m[sel, 0, None] - px[None]
                dy = m[sel, 1, None] - py[None]
                a_, b_, c_ = con[sel, 0, None], con[sel, 1, None], con[sel, 2, None]
                sigma = 0.5 * (a_ * dx * dx + c_ * dy * dy) + b_ * dx * dy
                al = np.minimum(max_alpha, op[sel, None] * np.exp(-sigma))
                al = np.where((sigma >= 0) & (al >= ALPHA_THRESHOLD), al, 0.0)
                t_after = np.cumprod(1.0 - al, axis=0)
                t_before = np.vstack([np.ones((1, px.size)), t_after[:-1]])
                contrib = t_after > 1e-4  # a prefix: T never increases
                w = np.where(contrib, al * t_before, 0.0)
                t_final = np.where(contrib, t_after, 1.0).min(axis=0)
                c = w.T @ col[sel]
                d = w.T @ dep[sel]
            a = 1.0 - t_final
            block = (slice(y0, y0 + len(ys)), slice(x0, x0 + len(xs)))
            rgb[block] = (c + t_final[:, None] * bg).reshape(len(ys), len(xs), 3)
            alpha[block] = a.reshape(len(ys), len(xs))
            depth[block] = (d / np.maximum(a, 1e-10)).reshape(len(ys), len(xs))
    return rgb, depth, alpha


def garden(fixtures_dir: Path, *, seed: int = 0, grid: int = 1) -> tuple[morphgs.GaussianScene, morphgs.Cameras]:
    """The garden points as Gaussians, built as gsplat's profiling does (fixtures/ATTRIBUTION.md):
    points inside [-2,2]^3, scales uniform in [1e-4, 0.02], random unit quaternions, opacities
    uniform in (0,1), colours from the file; `grid` > 1 tiles grid x grid copies offset by the
    crop extent (4) in x and y. Returns the scene and the file's 3 cameras (648x420)."""
    d = np.load(fixtures_dir / "gsplat_test_garden.npz")
    pts = d["means3d"].astype(np.float32)
    sel = np.all((pts >= -2) & (pts <= 2), axis=1)
    pts, colors = pts[sel], d["colors"][sel].astype(np.float64) / 255.0
    if grid > 1:
        h = grid // 2
        offs = [(gx * 4.0, gy * 4.0, 0.0) for gx in range(-h, h + 1) for gy in range(-h, h + 1)]
        pts = np.concatenate([pts + np.float32(o) for o in np.asarray(offs, np.float32)])
        colors = np.tile(colors, (grid * grid, 1))
    n = len(pts)
    rng = np.random.default_rng(seed)
    scales = rng.uniform(1e-4, 0.02, (n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    opac = rng.uniform(1e-3, 1 - 1e-3, n)
    scene = morphgs.GaussianScene.from_arrays(
        means=pts, quats=quats, log_scales=np.log(scales),
        opacity_logits=np.log(opac / (1 - opac)), sh0=(colors - 0.5) / 0.28209479177387814,
    )
    cams = morphgs.Cameras(world_to_camera=d["viewmats"], K=d["Ks"],
                           width=int(d["width"]), height=int(d["height"]))
    return scene, cams
