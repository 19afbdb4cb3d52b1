"""Float64 torch reference of the differentiable rasterizer, for the backward tests and
benchmarks.

Projection and SH colour are gsplat 1.5.3's pure-PyTorch functions (`gsplat.cuda._torch_impl`,
run on CPU with autograd); the activations are torch's; the blend is SPEC §4 step 7 written
densely in torch over the (pixel, Gaussian) pairs the Rust forward blended, in its order, with
its alpha-clamp decisions (gsplat's own backward test reuses the CUDA intersections the same
way). With those discrete decisions frozen the function is smooth, so torch autograd and
finite differences of it are the derivative our backward must produce.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import morphgs
from morphgs._core import DiffRasterizer


@dataclass
class Params:
    """Stored parameters (float32 arrays, the layout of GaussianScene)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh0: np.ndarray
    sh_rest: np.ndarray

    @classmethod
    def of(cls, scene: morphgs.GaussianScene) -> "Params":
        return cls(*(np.ascontiguousarray(getattr(scene, f), dtype=np.float32) for f in
                     ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest")))

    def arrays(self) -> tuple[np.ndarray, ...]:
        return (self.means, self.quats, self.log_scales, self.opacity_logits, self.sh0,
                self.sh_rest)

    @property
    def names(self) -> tuple[str, ...]:
        return ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest")


def random_scene(n: int, degree: int, seed: int, *, spread: float = 1.0,
                 log_scale: tuple[float, float] = (-4.0, -1.5)) -> morphgs.GaussianScene:
    """n random Gaussians in [-spread, spread]^3 with SH degree `degree`."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return morphgs.GaussianScene.from_arrays(
        means=rng.uniform(-spread, spread, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(*log_scale, (n, 3)),
        opacity_logits=rng.normal(0.0, 2.0, n),
        sh0=rng.normal(0.0, 0.8, (n, 3)),
        sh_rest=rng.normal(0.0, 0.3, (n, k, 3)) if degree else None,
    )


def front_camera(width: int, height: int, *, distance: float = 4.0, cx: float | None = None,
                 cy: float | None = None) -> morphgs.Camera:
    """A camera at z = -distance looking along +z."""
    c2w = np.eye(4)
    c2w[2, 3] = -distance
    return morphgs.Camera.from_c2w(c2w, fx=1.1 * width, fy=1.1 * width, width=width,
                                   height=height, cx=cx, cy=cy)


@dataclass
class Setup:
    """A camera and the render options of one check."""

    cam: morphgs.Camera
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_alpha: float = 0.99
    sh_degree: int | None = None
    antialiased: bool = False
    depth: str = "expected"


def rust_forward(p: Params, s: Setup) -> tuple[DiffRasterizer, tuple[np.ndarray, ...]]:
    """The Rust forward; returns the rasterizer (holding the state) and (rgb, depth, alpha)."""
    r = DiffRasterizer()
    rgb, depth, alpha, _ = r.forward(
        *p.arrays(), s.cam.world_to_camera, s.cam.K, s.cam.width, s.cam.height,
        near=s.cam.near, far=s.cam.far, background=s.background, max_alpha=s.max_alpha,
        sh_degree=s.sh_degree, antialiased=s.antialiased, depth=s.depth, absgrad=True)
    return r, (rgb, depth, alpha)


def rust_backward(r: DiffRasterizer, p: Params, w: dict[str, np.ndarray]) -> dict:
    """Our gradients for the loss sum(w_rgb rgb) + sum(w_depth depth) + sum(w_alpha alpha),
    the camera's (viewmat) included."""
    return r.backward(*p.arrays(), v_rgb=w["rgb"], v_depth=w["depth"], v_alpha=w["alpha"],
                      view=True, viewmat=True)


def loss_weights(s: Setup, seed: int) -> dict[str, np.ndarray]:
    """Random image gradients (the loss is linear in the images, so these are dL/d images)."""
    rng = np.random.default_rng(seed)
    h, w = s.cam.height, s.cam.width
    return {"rgb": rng.normal(size=(h, w, 3)).astype(np.float32),
            "depth": (0.3 * rng.normal(size=(h, w))).astype(np.float32),
            "alpha": rng.normal(size=(h, w)).astype(np.float32)}


class Reference:
    """L(params) in float64 (or `dtype`) with the Rust forward's blend decisions frozen."""

    def __init__(self, p: Params, s: Setup, r: DiffRasterizer, *, dtype: str = "float64"):
        import torch

        self.torch = torch
        self.dtype = getattr(torch, dtype)
        self.s = s
        pix, gid, clamped = r.contributions()
        order = np.argsort(pix, kind="stable")  # per pixel, blend order kept
        self.pix, self.gid, self.clamped = pix[order], gid[order], clamped[order]
        npix = s.cam.width * s.cam.height
        counts = np.bincount(self.pix, minlength=npix)
        self.maxlen = int(counts.max()) if len(counts) and counts.size else 0
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.slot = np.arange(len(self.pix)) - starts[self.pix]  # position within the pixel
        self.npix = npix
        self.degree = (p.sh_rest.shape[1] + 1) ** 0.5 - 1 if s.sh_degree is None else s.sh_degree
        self.degree = int(round(self.degree))

    def tensors(self, p: Params, requires_grad: bool = True) -> dict:
        t = self.torch
        return {n: t.tensor(a, dtype=self.dtype, requires_grad=requires_grad)
                for n, a in zip(p.names, p.arrays())}

    def project(self, x: dict, viewmat=None) -> dict:
        """Per-Gaussian projected values (float64, with autograd); given colours (x["colors"],
        post-activation) replace the SH colour."""
        t = self.torch
        from gsplat.cuda._torch_impl import (
            _fully_fused_projection,
            _quat_scale_to_covar_preci,
            _spherical_harmonics,
        )

        cam = self.s.cam
        covars, _ = _quat_scale_to_covar_preci(x["quats"], t.exp(x["log_scales"]),
                                               compute_covar=True, compute_preci=False)
        if viewmat is None:
            viewmat = t.tensor(np.asarray(cam.world_to_camera), dtype=self.dtype)
        viewmat = viewmat[None]
        ks = t.tensor(np.asarray(cam.K), dtype=self.dtype)[None]
        _, means2d, depths, conics, comp = _fully_fused_projection(
            x["means"], covars, viewmat, ks, cam.width, cam.height, eps2d=0.3,
            near_plane=cam.near, far_plane=cam.far, calc_compensations=self.s.antialiased)
        opac = t.sigmoid(x["opacity_logits"])
        if self.s.antialiased:
            assert comp is not None
            opac = opac * t.clamp(comp[0] ** 2, min=0.005 ** 2).sqrt()
        if "colors" in x:
            colors = x["colors"]
        else:
            campos = t.linalg.inv(viewmat[0])[:3, 3]
            coeffs = t.cat([x["sh0"][:, None, :], x["sh_rest"]], dim=1)
            nb = (self.degree + 1) ** 2
            rgb = _spherical_harmonics(self.degree, x["means"] - campos, coeffs[:, :nb])
            colors = t.clamp_min(rgb + 0.5, 0.0)
        return {"means2d": means2d[0], "conics": conics[0], "depths": depths[0],
                "opacities": opac, "colors": colors}

    def blend(self, g: dict, background=None) -> tuple:
        """(rgb (H,W,3), depth (H,W), alpha (H,W)) from per-Gaussian projected values."""
        t = self.torch
        s, cam = self.s, self.s.cam
        gid = t.from_numpy(self.gid)
        pix = t.from_numpy(self.pix)
        px = (pix % cam.width).to(self.dtype) + 0.5
        py = (pix // cam.width).to(self.dtype) + 0.5
        m = g["means2d"][gid]
        dx, dy = m[:, 0] - px, m[:, 1] - py
        con = g["conics"][gid]
        sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
        alpha = g["opacities"][gid] * t.exp(-sigma)
        alpha = t.where(t.from_numpy(self.clamped), t.full_like(alpha, s.max_alpha), alpha)
        # dense (pixel, position) layout, padded with alpha 0
        dense = t.zeros((self.npix, max(self.maxlen, 1)), dtype=self.dtype)
        idx = (pix, t.from_numpy(self.slot))
        dense = dense.index_put(idx, alpha)
        one_minus = 1.0 - dense
        t_after = t.cumprod(one_minus, dim=1)
        t_before = t.cat([t.ones((self.npix, 1), dtype=self.dtype), t_after[:, :-1]], dim=1)
        wts = (dense * t_before)[idx]
        t_final = t_after[:, -1]
        col = g["colors"][gid]
        c = t.zeros((self.npix, 3), dtype=self.dtype).index_add(0, pix, wts[:, None] * col)
        d = t.zeros(self.npix, dtype=self.dtype).index_add(0, pix, wts * g["depths"][gid])
        bg = (t.tensor(s.background, dtype=self.dtype) if background is None else background)
        rgb = c + t_final[:, None] * bg
        a = 1.0 - t_final
        depth = d / t.clamp(a, min=1e-10) if s.depth == "expected" else d
        h, w = cam.height, cam.width
        return rgb.reshape(h, w, 3), depth.reshape(h, w), a.reshape(h, w)

    def loss(self, x: dict, w: dict, background=None):
        t = self.torch
        rgb, depth, alpha = self.blend(self.project(x), background)
        return ((rgb * t.from_numpy(w["rgb"]).to(self.dtype)).sum()
                + (depth * t.from_numpy(w["depth"]).to(self.dtype)).sum()
                + (alpha * t.from_numpy(w["alpha"]).to(self.dtype)).sum())

    def grads(self, p: Params, w: dict) -> tuple[dict, dict]:
        """Autograd gradients of the parameters, and of the per-Gaussian projected values."""
        t = self.torch
        x = self.tensors(p)
        g = self.project(x)
        for v in g.values():
            v.retain_grad()
        bg = t.tensor(self.s.background, dtype=self.dtype, requires_grad=True)
        rgb, depth, alpha = self.blend(g, bg)
        loss = ((rgb * t.from_numpy(w["rgb"]).to(self.dtype)).sum()
                + (depth * t.from_numpy(w["depth"]).to(self.dtype)).sum()
                + (alpha * t.from_numpy(w["alpha"]).to(self.dtype)).sum())
        loss.backward()
        out = {n: x[n].grad.numpy() for n in p.names}
        out["background"] = bg.grad.numpy()
        inter = {n: (v.grad.numpy() if v.grad is not None else np.zeros(v.shape))
                 for n, v in g.items()}
        return out, inter
