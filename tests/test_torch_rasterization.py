"""`morphgs.torch.rasterization`: gsplat's API and conventions on the CPU backward.

Gradients against the float64 reference (gsplat's torch projection and SH, dense blend) for
gsplat's activated inputs, the render modes, gsplat's own DefaultStrategy densifying from our
meta, and a real optimisation that lowers its loss.
"""

from __future__ import annotations

import numpy as np
import pytest

import morphgs

torch = pytest.importorskip("torch")
pytest.importorskip("gsplat")

from backward_reference import Params, Reference, Setup, front_camera, random_scene  # noqa: E402
from morphgs.torch import rasterization  # noqa: E402


def cameras(n: int, width: int, height: int) -> tuple[list[morphgs.Camera], torch.Tensor, torch.Tensor]:
    cams = [morphgs.Camera.look_at(np.array([0.6 * i - 0.3, -0.2 * i, -4.0]), np.zeros(3),
                                   fov_y_degrees=45, width=width, height=height)
            for i in range(n)]
    # float64 cameras: the reference below sees exactly the same ones
    viewmats = torch.tensor(np.stack([c.world_to_camera for c in cams]), dtype=torch.float64)
    ks = torch.tensor(np.stack([c.K for c in cams]), dtype=torch.float64)
    return cams, viewmats, ks


def gsplat_inputs(scene: morphgs.GaussianScene, dtype: torch.dtype = torch.float32) -> dict:
    """gsplat's activated parameters of a scene, as leaf tensors."""
    coeffs = np.concatenate([np.array(scene.sh0)[:, None], np.array(scene.sh_rest)], axis=1)
    vals = {"means": scene.means, "quats": scene.quats,
            "scales": np.exp(np.array(scene.log_scales, dtype=np.float64)),
            "opacities": 1 / (1 + np.exp(-np.array(scene.opacity_logits, dtype=np.float64))),
            "colors": coeffs}
    return {k: torch.tensor(np.asarray(v), dtype=dtype, requires_grad=True) for k, v in vals.items()}


def reference_grads(x: dict, cams: list[morphgs.Camera], bg: np.ndarray, sh_degree: int | None,
                    w_img: torch.Tensor, w_alpha: torch.Tensor, render_mode: str,
                    viewmats: torch.Tensor | None = None) -> dict:
    """Autograd of the float64 reference for gsplat's inputs, summed over cameras."""
    f32 = {k: v.detach().float() for k, v in x.items()}
    n = len(f32["means"])
    stored = Params(*(np.ascontiguousarray(a.numpy()) for a in (
        f32["means"], f32["quats"], torch.log(f32["scales"]),
        torch.logit(f32["opacities"]).clamp(-30, 30),
        f32["colors"][:, 0] if sh_degree is not None else torch.zeros(n, 3),
        f32["colors"][:, 1:(sh_degree + 1) ** 2] if sh_degree is not None else torch.zeros(n, 0, 3),
    )))
    leaves = {k: v.detach().double().requires_grad_(True) for k, v in x.items()}
    bgt = torch.tensor(bg, dtype=torch.float64, requires_grad=True)
    vm = None if viewmats is None else viewmats.detach().double().requires_grad_(True)
    loss = torch.zeros((), dtype=torch.float64)
    for c, cam in enumerate(cams):
        setup = Setup(cam, background=tuple(bg[c]), sh_degree=sh_degree, depth="accumulated")
        r = morphgs._core.DiffRasterizer()
        r.forward(*stored.arrays(), cam.world_to_camera, cam.K, cam.width, cam.height,
                  background=tuple(bg[c]), sh_degree=sh_degree, depth="accumulated",
                  colors=None if sh_degree is not None else stored_colors(x))
        ref = Reference(stored, setup, r)
        t = {"means": leaves["means"], "quats": leaves["quats"],
             "log_scales": torch.log(leaves["scales"]),
             "opacity_logits": torch.logit(leaves["opacities"])}
        if sh_degree is None:
            t["colors"] = leaves["colors"]
        else:
            t["sh0"] = leaves["colors"][:, 0]
            t["sh_rest"] = leaves["colors"][:, 1:]
        rgb, depth, alpha = ref.blend(ref.project(t, viewmat=None if vm is None else vm[c]), bgt[c])
        ed = depth / alpha.clamp(min=1e-10)
        img = torch.cat([rgb, ed[..., None]], dim=-1) if render_mode == "RGB+ED" else rgb
        loss = loss + (img * w_img[c].double()).sum() + (alpha * w_alpha[c].double()).sum()
    loss.backward()
    out = {k: v.grad.numpy() for k, v in leaves.items()}
    out["backgrounds"] = bgt.grad.numpy()
    if vm is not None:
        out["viewmats"] = vm.grad.numpy()
    return out


def stored_colors(x: dict) -> np.ndarray:
    return np.ascontiguousarray(x["colors"].detach().float().numpy())


@pytest.mark.parametrize("sh_degree", [3, None])
def test_gradients_of_gsplat_inputs_match_the_reference(sh_degree: int | None) -> None:
    scene = random_scene(250, 3, seed=21)
    x = gsplat_inputs(scene)
    if sh_degree is None:
        x["colors"] = torch.tensor(np.random.default_rng(0).uniform(0, 1, (len(scene), 3)),
                                   dtype=torch.float32, requires_grad=True)
    cams, viewmats, ks = cameras(2, 48, 40)
    bg = np.array([[0.1, 0.2, 0.3], [1.0, 0.5, 0.0]])
    bgt = torch.tensor(bg, dtype=torch.float32, requires_grad=True)
    mode = "RGB+ED" if sh_degree is not None else "RGB"
    img, alpha, meta = rasterization(x["means"], x["quats"], x["scales"], x["opacities"],
                                     x["colors"], viewmats, ks, 48, 40, sh_degree=sh_degree,
                                     backgrounds=bgt, render_mode=mode)
    assert img.shape == (2, 40, 48, 4 if mode == "RGB+ED" else 3) and alpha.shape == (2, 40, 48, 1)
    rng = np.random.default_rng(1)
    w_img = torch.tensor(rng.normal(size=img.shape), dtype=torch.float32)
    w_img[..., 3:] *= 0.2
    w_alpha = torch.tensor(rng.normal(size=alpha.shape[:-1]), dtype=torch.float32)
    ((img * w_img).sum() + (alpha[..., 0] * w_alpha).sum()).backward()
    want = reference_grads(x, cams, bg, sh_degree, w_img, w_alpha, mode)
    vis = (meta["radii"] > 0).all(-1).any(0).numpy()
    assert vis.sum() > 50
    for name in ["means", "quats", "scales", "opacities", "colors"]:
        got = x[name].grad.numpy()[vis]
        ref = want[name][vis]
        if name == "colors" and sh_degree is not None:
            got, ref = got[:, :16], ref[:, :16]
        scale = np.abs(ref).max()
        assert np.abs(got - ref).max() <= 1e-3 * scale, name
    np.testing.assert_allclose(bgt.grad.numpy(), want["backgrounds"], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("sh_degree", [3, 0])
def test_viewmat_gradients_match_the_reference(sh_degree: int) -> None:
    """gsplat's v_viewmats: through the camera-space means and covariances and, with SH, the
    camera centre (the translation of inverse(viewmats), as gsplat takes it)."""
    scene = random_scene(250, 3, seed=22)
    x = gsplat_inputs(scene)
    cams, viewmats, ks = cameras(2, 48, 40)
    pose = viewmats.clone().requires_grad_(True)
    bg = np.zeros((2, 3))
    img, alpha, meta = rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                     pose, ks, 48, 40, sh_degree=sh_degree, render_mode="RGB+ED")
    rng = np.random.default_rng(3)
    w_img = torch.tensor(rng.normal(size=img.shape), dtype=torch.float32)
    w_img[..., 3:] *= 0.2
    w_alpha = torch.tensor(rng.normal(size=alpha.shape[:-1]), dtype=torch.float32)
    ((img * w_img).sum() + (alpha[..., 0] * w_alpha).sum()).backward()
    want = reference_grads(x, cams, bg, sh_degree, w_img, w_alpha, "RGB+ED", viewmats=viewmats)["viewmats"]
    got = pose.grad.numpy()
    assert got.shape == (2, 4, 4) and pose.grad.dtype == torch.float64
    for c in range(2):
        scale = np.abs(want[c]).max()
        assert scale > 0
        assert np.abs(got[c] - want[c]).max() <= 2e-3 * scale, (c, got[c], want[c])
    if sh_degree == 0:  # no view dependence: the bottom row gets nothing
        np.testing.assert_array_equal(got[:, 3], 0.0)
    # the other parameters' gradients do not change when the pose is differentiated too
    first = {k: v.grad.clone() for k, v in x.items()}
    for v in x.values():
        v.grad = None
    img2, alpha2, _ = rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                    viewmats, ks, 48, 40, sh_degree=sh_degree, render_mode="RGB+ED")
    ((img2 * w_img).sum() + (alpha2[..., 0] * w_alpha).sum()).backward()
    for k, v in x.items():
        assert torch.equal(v.grad, first[k]), k


def test_pose_optimisation_recovers_a_shifted_camera() -> None:
    """Render a target, shift the camera, and let Adam on the viewmat's translation bring the
    render back (a real optimisation through the pose gradient)."""
    scene = random_scene(400, 0, seed=5)
    x = {k: v.detach() for k, v in gsplat_inputs(scene).items()}
    _, viewmats, ks = cameras(1, 48, 40)
    target, _, _ = rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                 viewmats, ks, 48, 40, sh_degree=0)
    shift = torch.zeros_like(viewmats)
    shift[0, :3, 3] = torch.tensor([0.15, -0.1, 0.0], dtype=viewmats.dtype)
    t = (viewmats[0, :3, 3] + shift[0, :3, 3]).clone().requires_grad_(True)
    opt = torch.optim.Adam([t], lr=0.01)
    losses = []
    for _ in range(60):
        vm = torch.cat([torch.cat([viewmats[0, :3, :3], t[:, None]], dim=1), viewmats[0, 3:]], dim=0)[None]
        img, _, _ = rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                  vm, ks, 48, 40, sh_degree=0)
        loss = ((img - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    err0 = float(shift[0, :3, 3].norm())
    err = float((t.detach() - viewmats[0, :3, 3]).norm())
    assert losses[-1] < 0.2 * losses[0] and err < 0.3 * err0, (losses[0], losses[-1], err0, err)


def test_meta_follows_gsplat_and_means2d_grad_is_set() -> None:
    scene = random_scene(300, 0, seed=2)
    x = gsplat_inputs(scene)
    _, viewmats, ks = cameras(2, 40, 32)
    img, alpha, meta = rasterization(x["means"], x["quats"], x["scales"], x["opacities"],
                                     x["colors"], viewmats, ks, 40, 32, sh_degree=0, absgrad=True)
    n = len(scene)
    assert meta["radii"].shape == (2, n, 2) and meta["radii"].dtype == torch.int32
    assert meta["means2d"].shape == (2, n, 2) and meta["depths"].shape == (2, n)
    assert meta["conics"].shape == (2, n, 3) and meta["opacities"].shape == (2, n)
    assert (meta["width"], meta["height"], meta["n_cameras"], meta["tile_size"]) == (40, 32, 2, 16)
    meta["means2d"].retain_grad()  # what gsplat's strategies do before backward
    img.sum().backward()
    g = meta["means2d"].grad
    vis = (meta["radii"] > 0).all(-1)
    assert g.shape == (2, n, 2) and g[vis].abs().sum() > 0 and not g[~vis].any()
    # absgrad sums absolute per-pixel values: at least the absolute sum
    assert torch.all(meta["means2d"].absgrad >= g.abs() - 1e-5)


def test_render_modes_give_depth_channels() -> None:
    scene = random_scene(200, 1, seed=3)
    x = gsplat_inputs(scene)
    _, viewmats, ks = cameras(1, 32, 24)
    args = (x["means"], x["quats"], x["scales"], x["opacities"], x["colors"], viewmats, ks, 32, 24)
    with torch.no_grad():
        rgb, a, _ = rasterization(*args, sh_degree=1, render_mode="RGB")
        d, _, _ = rasterization(*args, sh_degree=1, render_mode="D")
        ed, _, _ = rasterization(*args, sh_degree=1, render_mode="ED")
        both, _, _ = rasterization(*args, sh_degree=1, render_mode="RGB+ED")
    assert d.shape == ed.shape == (1, 24, 32, 1) and both.shape == (1, 24, 32, 4)
    torch.testing.assert_close(ed, d / a.clamp(min=1e-10))
    torch.testing.assert_close(both[..., :3], rgb)
    cover = a[..., 0] > 0.5
    assert torch.all(ed[..., 0][cover] > 2.0) and torch.all(ed[..., 0][cover] < 6.0)


def test_float64_inputs_get_float64_gradients() -> None:
    scene = random_scene(100, 0, seed=4)
    x = gsplat_inputs(scene, dtype=torch.float64)
    _, viewmats, ks = cameras(1, 24, 24)
    img, _, _ = rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                              viewmats.double(), ks.double(), 24, 24, sh_degree=0)
    assert img.dtype == torch.float64
    img.sum().backward()
    assert all(x[k].grad.dtype == torch.float64 for k in x)


def test_unsupported_gsplat_options_are_clear_errors() -> None:
    scene = random_scene(10, 0, seed=1)
    x = gsplat_inputs(scene)
    _, viewmats, ks = cameras(1, 16, 16)
    args = (x["means"], x["quats"], x["scales"], x["opacities"], x["colors"], viewmats, ks, 16, 16)
    for kw, word in [({"eps2d": 0.1}, "eps2d"), ({"camera_model": "fisheye"}, "camera_model"),
                     ({"render_mode": "N"}, "render_mode"), ({"tile_size": 8}, "tile_size"),
                     ({"sh_degree": 5}, "sh_degree")]:
        with pytest.raises(morphgs.MorphgsError, match=word):
            rasterization(*args, **kw)
    with pytest.raises(morphgs.MorphgsError, match="colors"):
        rasterization(*args[:4], x["colors"][:, :1], *args[5:], sh_degree=1)
    with pytest.raises(morphgs.MorphgsError, match="means"):
        rasterization(x["means"][None], *args[1:], sh_degree=0)
    # intrinsics gradients are refused, not silently dropped; detached (or no_grad) Ks run
    k = ks.clone().requires_grad_()
    with pytest.raises(morphgs.MorphgsError, match="Ks.detach"):
        rasterization(*args[:6], k, *args[7:], sh_degree=0)
    with torch.no_grad():
        rasterization(*args[:6], k, *args[7:], sh_degree=0)
    rasterization(*args[:6], k.detach(), *args[7:], sh_degree=0)


def test_gsplat_default_strategy_trains_and_densifies_on_our_meta() -> None:
    """A real optimisation with gsplat's own DefaultStrategy: Adam steps lower the loss against
    target images of a ground-truth scene, and the strategy grows Gaussians from our
    means2d gradients."""
    from gsplat.strategy import DefaultStrategy

    truth = random_scene(300, 0, seed=8, log_scale=(-3.5, -2.0))
    cams, viewmats, ks = cameras(3, 48, 40)
    with torch.no_grad():
        t = gsplat_inputs(truth)
        targets, _, _ = rasterization(t["means"], t["quats"], t["scales"], t["opacities"],
                                      t["colors"], viewmats, ks, 48, 40, sh_degree=0)
    start = random_scene(150, 0, seed=9, log_scale=(-3.0, -2.0))
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.tensor(np.array(start.means))),
        "quats": torch.nn.Parameter(torch.tensor(np.array(start.quats))),
        "scales": torch.nn.Parameter(torch.tensor(np.array(start.log_scales))),
        "opacities": torch.nn.Parameter(torch.tensor(np.array(start.opacity_logits))),
        "colors": torch.nn.Parameter(torch.tensor(np.array(start.sh0))[:, None]),
    })
    lrs = {"means": 1e-2, "quats": 1e-2, "scales": 1e-2, "opacities": 5e-2, "colors": 2.5e-2}
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": lr, "name": k}], eps=1e-15)
                  for k, lr in lrs.items()}
    strategy = DefaultStrategy(refine_start_iter=5, refine_every=10, refine_stop_iter=100,
                               grow_grad2d=1e-5, reset_every=10_000, verbose=False)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    losses = []
    for step in range(40):
        img, _, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                     torch.sigmoid(params["opacities"]), params["colors"],
                                     viewmats, ks, 48, 40, sh_degree=0)
        loss = (img - targets).abs().mean()
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        losses.append(float(loss.detach()))
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info)
    assert len(params["means"]) > 150, "no Gaussian was duplicated or split"
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5]), losses
