"""`rasterization`: gsplat's rasterization API on morphgs's CPU forward and backward passes.

The Rust side works on the stored parameters; this module converts gsplat's activated inputs
(scales, opacities) to them and maps the gradients back (the core returns dL/d scales and
dL/d opacities directly, so no division by the activation's derivative is needed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from morphgs._core import DiffRasterizer, MorphgsError

_RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
# logits beyond +-30 give opacity 1 or below the 1/255 cull in float32: clamping keeps an
# opacity of exactly 0 or 1 finite (a non-finite stored value would drop the Gaussian)
_LOGIT_CLAMP = 30.0
# rasterizers (each holding reusable buffers: about 50 MB for a 112k-Gaussian 648x420 frame,
# 400 MB for 2.8M Gaussians at 1080p) kept for the next call; a batch of more cameras makes
# new ones
_POOL: list[DiffRasterizer] = []
_POOL_MAX = 4


def _take() -> DiffRasterizer:
    return _POOL.pop() if _POOL else DiffRasterizer()


def _give(r: DiffRasterizer) -> None:
    if len(_POOL) < _POOL_MAX:
        _POOL.append(r)


def _np32(t: Tensor) -> np.ndarray:
    """A float32 C-contiguous NumPy view (a copy only when the tensor is not one already)."""
    return t.detach().to(torch.float32).contiguous().numpy()


@dataclass
class _Setup:
    width: int
    height: int
    viewmats: np.ndarray  # (C,4,4) float64
    Ks: np.ndarray  # (C,3,3) float64
    near: float
    far: float
    sh_degree: int | None
    max_alpha: float
    antialiased: bool
    absgrad: bool
    means2d: Tensor  # the leaf meta["means2d"]; its .grad is set by the backward
    rasterizers: list[DiffRasterizer]
    arrays: tuple[np.ndarray, ...] = ()
    colors: np.ndarray | None = None


class _Rasterize(torch.autograd.Function):
    """(rgb (C,H,W,3), accumulated depth (C,H,W), alpha (C,H,W)) of every camera."""

    @staticmethod
    def forward(ctx: Any, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                sh0: Tensor, sh_rest: Tensor, colors: Tensor | None, backgrounds: Tensor | None,
                viewmats: Tensor, setup: _Setup) -> tuple[Tensor, Tensor, Tensor]:
        log_scales = torch.log(scales.detach().to(torch.float32))
        logits = torch.logit(opacities.detach().to(torch.float32)).clamp(-_LOGIT_CLAMP, _LOGIT_CLAMP)
        setup.arrays = (_np32(means), _np32(quats), _np32(log_scales), _np32(logits), _np32(sh0),
                        _np32(sh_rest))
        setup.colors = None if colors is None else _np32(colors)
        rgbs, depths, alphas = [], [], []
        for c in range(setup.viewmats.shape[0]):
            r = _take()
            setup.rasterizers.append(r)
            bg = (0.0, 0.0, 0.0)
            if backgrounds is not None:
                bg = (float(backgrounds[c, 0]), float(backgrounds[c, 1]), float(backgrounds[c, 2]))
            rgb, depth, alpha, _ = r.forward(
                *setup.arrays, setup.viewmats[c], setup.Ks[c], setup.width, setup.height,
                near=setup.near, far=setup.far, background=bg, max_alpha=setup.max_alpha,
                sh_degree=setup.sh_degree, antialiased=setup.antialiased, colors=setup.colors,
                depth="accumulated", absgrad=setup.absgrad)
            rgbs.append(torch.from_numpy(rgb))
            depths.append(torch.from_numpy(depth))
            alphas.append(torch.from_numpy(alpha))
        ctx.setup = setup
        ctx.dtypes = [None if t is None else t.dtype
                      for t in (means, quats, scales, opacities, sh0, sh_rest, colors, backgrounds, viewmats)]
        ctx.set_materialize_grads(False)
        dtype = means.dtype
        return (torch.stack(rgbs).to(dtype), torch.stack(depths).to(dtype),
                torch.stack(alphas).to(dtype))

    @staticmethod
    def backward(ctx: Any, v_rgb: Tensor | None, v_depth: Tensor | None,
                 v_alpha: Tensor | None) -> tuple[Tensor | None, ...]:
        setup: _Setup = ctx.setup
        n_cams = len(setup.rasterizers)
        totals: dict[str, np.ndarray] = {}
        v_bg, m2d, m2d_abs, v_view = [], [], [], []
        want_view = bool(ctx.needs_input_grad[8])
        for c, r in enumerate(setup.rasterizers):
            pick = (lambda v: None if v is None else _np32(v[c]))  # noqa: E731
            out = r.backward(*setup.arrays, colors=setup.colors, v_rgb=pick(v_rgb),
                             v_depth=pick(v_depth), v_alpha=pick(v_alpha), view=True,
                             viewmat=want_view, cameras_per_step=float(n_cams))
            if want_view:
                v_view.append(out["viewmat"])
            # cameras add up in camera order (deterministic)
            for k in ("means", "quats", "scales", "opacities", "sh0", "sh_rest", "colors"):
                if k in out:
                    totals[k] = out[k] if k not in totals else totals[k] + out[k]
            v_bg.append(out["background"])
            m2d.append(out["means2d"])
            m2d_abs.append(out["means2d_abs"])
            _give(r)
        setup.rasterizers.clear()
        leaf = setup.means2d
        g2d = torch.from_numpy(np.stack(m2d)).to(leaf.dtype)
        leaf.grad = g2d if leaf.grad is None else leaf.grad + g2d
        if setup.absgrad:
            a2d = torch.from_numpy(np.stack(m2d_abs)).to(leaf.dtype)
            prev = getattr(leaf, "absgrad", None)
            leaf.absgrad = a2d if prev is None else prev + a2d  # type: ignore[attr-defined]
        dt = ctx.dtypes

        def grad(k: str, i: int) -> Tensor | None:
            if not ctx.needs_input_grad[i] or k not in totals:
                return None
            return torch.from_numpy(totals[k]).to(dt[i])

        v_backgrounds = None
        if ctx.needs_input_grad[7]:
            v_backgrounds = torch.from_numpy(np.stack(v_bg)).to(dt[7])
        v_viewmats = torch.from_numpy(np.stack(v_view)).to(dt[8]) if want_view else None
        return (grad("means", 0), grad("quats", 1), grad("scales", 2), grad("opacities", 3),
                grad("sh0", 4), grad("sh_rest", 5), grad("colors", 6), v_backgrounds, v_viewmats, None)


def _unsupported(name: str, value: object, why: str) -> MorphgsError:
    return MorphgsError(f"morphgs.torch.rasterization: {name}={value!r} is not supported ({why})")


def rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    distributed: bool = False,
    camera_model: str = "pinhole",
    segmented: bool = False,
    covars: Tensor | None = None,
    with_ut: bool = False,
    with_eval3d: bool = False,
    *,
    max_alpha: float = 0.99,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Rasterize N Gaussians to C images on the CPU, differentiably, as ``gsplat.rasterization``.

    The arguments, shapes and outputs are gsplat 1.5.3's (see its docstring): activated
    ``scales`` and ``opacities``, ``quats`` (w,x,y,z, normalised inside), ``colors`` as SH
    coefficients (N,K,3) with ``sh_degree`` or post-activation colours (N,3) without, OpenCV
    ``viewmats`` (C,4,4) world-to-camera and ``Ks`` (C,3,3). Gradients flow to means, quats,
    scales, opacities, colors, backgrounds and viewmats (pose optimisation; the camera centre's
    path through the SH view directions included), not to Ks (Ks that require grad are refused
    rather than silently detached). As in gsplat,
    ``meta["means2d"].grad`` holds dL/d(projected means) (C,N,2) after ``backward()`` (and
    ``.absgrad`` with ``absgrad=True``), which gsplat's densification strategies read.

    Args:
        means, quats, scales, opacities, colors, viewmats, Ks, width, height: as gsplat.
        near_plane, far_plane, eps2d (0.3 only), sh_degree, backgrounds (C,3), render_mode
            ("RGB", "D", "ED", "RGB+D", "RGB+ED"), absgrad, rasterize_mode ("classic",
            "antialiased"): as gsplat.
        packed, segmented, channel_chunk: accepted and ignored (meta is gsplat's unpacked form).
        max_alpha: per-Gaussian alpha cap: 0.99 (INRIA, gsplat >= 1.6; the morphgs default) or
            0.999 (gsplat 1.5.3).

    Returns:
        (render_colors (C,H,W,X), render_alphas (C,H,W,1), meta dict with radii (C,N,2) int32,
        means2d (C,N,2), depths (C,N), conics (C,N,3), opacities (C,N), width, height,
        n_cameras, tile_size, tile_width, tile_height and gsplat's other ids as None).

    Raises:
        MorphgsError: an option gsplat has that this rasterizer does not (distortion, other
            camera models, batch dimensions, ...), tensors not on the CPU, or bad shapes.
    """
    if render_mode not in _RENDER_MODES:
        raise _unsupported("render_mode", render_mode, f"use one of {_RENDER_MODES}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise _unsupported("rasterize_mode", rasterize_mode, "use 'classic' or 'antialiased'")
    for name, value, ok, why in [
        ("eps2d", eps2d, eps2d == 0.3, "the rasterizer's low-pass filter is fixed at 0.3"),
        ("tile_size", tile_size, tile_size == 16, "tiles are 16x16"),
        ("radius_clip", radius_clip, radius_clip == 0.0, "no radius clipping"),
        ("sparse_grad", sparse_grad, not sparse_grad, "gradients are dense"),
        ("distributed", distributed, not distributed, "one process renders everything"),
        ("camera_model", camera_model, camera_model == "pinhole", "pinhole cameras only"),
        ("covars", "<tensor>", covars is None, "pass quats and scales"),
        ("with_ut", with_ut, not with_ut, "EWA projection only"),
        ("with_eval3d", with_eval3d, not with_eval3d, "2D evaluation only"),
    ]:
        if not ok:
            raise _unsupported(name, value, why)
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities,
               "colors": colors, "viewmats": viewmats, "Ks": Ks}
    if backgrounds is not None:
        tensors["backgrounds"] = backgrounds
    for name, t in tensors.items():
        if t.device.type != "cpu":
            raise MorphgsError(f"morphgs.torch.rasterization runs on the CPU: {name} is on {t.device}")
    n = means.shape[0] if means.dim() == 2 else -1
    expect = [("means", means, (n, 3)), ("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
              ("opacities", opacities, (n,))]
    for name, t, shape in expect:
        if n < 0 or tuple(t.shape) != shape:
            raise MorphgsError(f"{name} must have shape {shape} (no batch dimensions), got "
                               f"{tuple(t.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4) or Ks.shape != (viewmats.shape[0], 3, 3):
        raise MorphgsError(f"viewmats must be (C,4,4) and Ks (C,3,3), got {tuple(viewmats.shape)} "
                           f"and {tuple(Ks.shape)}")
    if torch.is_grad_enabled() and Ks.requires_grad:
        # gsplat gives Ks no gradient either; detaching silently would leave an intrinsics
        # optimiser with grad None and no word why
        raise MorphgsError("morphgs.torch.rasterization has no gradients for Ks (intrinsics optimisation): "
                           "pass Ks.detach()")
    n_cams = viewmats.shape[0]
    if backgrounds is not None and tuple(backgrounds.shape) != (n_cams, 3):
        raise MorphgsError(f"backgrounds must be (C,3) = ({n_cams},3), got {tuple(backgrounds.shape)}")

    given: Tensor | None
    if sh_degree is None:
        if colors.dim() != 2 or tuple(colors.shape) != (n, 3):
            raise MorphgsError(f"without sh_degree, colors must be (N,3) = ({n},3) post-activation "
                               f"colours, got {tuple(colors.shape)}")
        given = colors
        sh0 = torch.zeros((n, 3), dtype=torch.float32)
        sh_rest = torch.zeros((n, 0, 3), dtype=torch.float32)
    else:
        if not 0 <= sh_degree <= 3:
            raise _unsupported("sh_degree", sh_degree, "SH degrees 0-3")
        nb = (sh_degree + 1) ** 2
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[2] != 3 or colors.shape[1] < nb:
            raise MorphgsError(f"with sh_degree={sh_degree}, colors must be (N,K,3) SH coefficients "
                               f"with K >= {nb}, got {tuple(colors.shape)}")
        given = None
        sh0 = colors[:, 0, :]
        sh_rest = colors[:, 1:nb, :]

    means2d = torch.zeros((n_cams, n, 2), dtype=means.dtype, requires_grad=True)
    setup = _Setup(
        width=int(width), height=int(height),
        viewmats=viewmats.detach().to(torch.float64).contiguous().numpy(),
        Ks=Ks.detach().to(torch.float64).contiguous().numpy(),
        near=float(near_plane), far=float(far_plane), sh_degree=sh_degree,
        max_alpha=float(max_alpha), antialiased=rasterize_mode == "antialiased",
        absgrad=absgrad, means2d=means2d, rasterizers=[],
    )
    rgb, depth, alpha = _Rasterize.apply(means, quats, scales, opacities, sh0, sh_rest, given,
                                         backgrounds, viewmats, setup)
    # projected values for meta, from the rasterizers' saved state
    proj = [r.projection() for r in setup.rasterizers]
    if not torch.is_grad_enabled() or not rgb.requires_grad:
        for r in setup.rasterizers:
            _give(r)
        setup.rasterizers.clear()
    with torch.no_grad():
        means2d.copy_(torch.from_numpy(np.stack([p["means2d"] for p in proj])))
    alphas = alpha[..., None]
    acc_depth = depth[..., None]
    exp_depth = acc_depth / alphas.clamp(min=1e-10)
    if render_mode == "RGB":
        out = rgb
    elif render_mode == "D":
        out = acc_depth
    elif render_mode == "ED":
        out = exp_depth
    elif render_mode == "RGB+D":
        out = torch.cat([rgb, acc_depth], dim=-1)
    else:
        out = torch.cat([rgb, exp_depth], dim=-1)
    tile_w, tile_h = -(-int(width) // 16), -(-int(height) // 16)
    meta: dict[str, Any] = {
        "batch_ids": None,
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": torch.from_numpy(np.stack([p["radii"] for p in proj])),
        "means2d": means2d,
        "depths": torch.from_numpy(np.stack([p["depths"] for p in proj])).to(means.dtype),
        "conics": torch.from_numpy(np.stack([p["conics"] for p in proj])).to(means.dtype),
        "opacities": torch.from_numpy(np.stack([p["opacities"] for p in proj])).to(means.dtype),
        "tile_width": tile_w,
        "tile_height": tile_h,
        "width": int(width),
        "height": int(height),
        "tile_size": 16,
        "n_batches": 1,
        "n_cameras": n_cams,
    }
    return out, alphas, meta
