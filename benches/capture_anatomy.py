"""Where a real capture's sparse-view fit fails, and which of its Gaussians hold the error
(docs/artifacts.md, "What a real capture's sparse fit is made of"): the way benches/haze_anatomy.py
took the built-in rooms' sparse fits apart, on photos.

    python benches/capture_anatomy.py                       # the committed skull, every 4th photo
    python benches/capture_anatomy.py CAPTURE --every 6 --work /tmp/anatomy

A dense fit (every photo, 5,000 steps) and a sparse fit (every `--every`-th photo, 3,000 steps),
the toy study's fit settings; the other photos are held out. Printed: the held-out PSNR against
the photos and against the dense fit's renders; per group of the sparse fit's Gaussians (how many
training views see the centre, depth against the dense surface in the nearest training view that
sees it, footprint there, opacity, and those hidden in every training view yet seen held out,
found by autograd through `morphgs.torch.rasterization`), the held-out PSNR without the group;
with the view-dependent colour (SH bands 1-3) removed; each fit's geometry with the other's
colours (nearest centre: is the failure geometry or appearance?); and the held-out residual's luminance sign,
its share on the object (dense alpha > 0.5) and at see-through pixels. Fits resume from --work.
Reports; asserts nothing. Needs torch for the hidden-Gaussian row (skipped without it).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

import morphgs
from morphgs.ablation.stages.common import fit_config
from morphgs.camera import Cameras
from morphgs.fit import fit
from morphgs.fit.data import load_posed_images

HERE = Path(__file__).resolve().parent
LUMA = np.array([0.299, 0.587, 0.114])


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / max(float(np.mean((np.clip(a, 0, 1) - b) ** 2)), 1e-12)))


def q(a: np.ndarray) -> str:
    a = a[np.isfinite(a)]
    return " / ".join(f"{x:.3g}" for x in np.quantile(a, [0.1, 0.5, 0.9])) if len(a) else "-"


def in_training_views(scene: Any, tcams: list[Any], dense_depth: np.ndarray) -> dict[str, np.ndarray]:
    """Per Gaussian: training views whose image holds its centre, log(z / dense surface depth) and
    footprint (pixels, largest scale) in the nearest of them."""
    means = np.asarray(scene.means, np.float64)
    largest = np.asarray(scene.scales, np.float64).max(1)
    n = len(means)
    seen, best = np.zeros(n, int), np.full(n, np.inf)
    rel, foot = np.full(n, np.nan), np.full(n, np.nan)
    for k, c in enumerate(tcams):
        w2c = np.asarray(c.world_to_camera, np.float64)
        p = means @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = c.fx * p[:, 0] / z + c.cx, c.fy * p[:, 1] / z + c.cy
        inside = (z > 0.01) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        seen += inside
        closer = inside & (z < best)
        best[closer] = z[closer]
        ui = np.clip(u[closer].astype(int), 0, c.width - 1)
        vi = np.clip(v[closer].astype(int), 0, c.height - 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel[closer] = np.log(z[closer] / dense_depth[k][vi, ui].reshape(-1))
        foot[closer] = c.fx * largest[closer] / z[closer]
    return {"seen": seen, "rel": rel, "foot": foot}


def blend_weights(scene: Any, cams: list[Any]) -> np.ndarray | None:
    """(views, N): each Gaussian's summed blend weight (pixels' worth) per view: the gradient of a
    channel's sum with respect to its colour. None without torch."""
    try:
        import torch

        from morphgs.torch import rasterization
    except ImportError:
        return None
    vm = torch.tensor(np.stack([np.asarray(c.world_to_camera, np.float32) for c in cams]))
    ks = torch.tensor(np.stack([np.array([[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]], np.float32) for c in cams]))
    means, quats, scales = (torch.tensor(np.asarray(a, np.float32)) for a in (scene.means, scene.quats, scene.scales))
    opac = torch.tensor(np.asarray(scene.opacities, np.float32).reshape(-1))
    col = torch.full((len(scene), 3), 0.5, requires_grad=True)
    out: list[np.ndarray] = []
    for v, c in enumerate(cams):
        col.grad = None
        img, _, _ = rasterization(means, quats, scales, opac, col, vm[v:v + 1], ks[v:v + 1], c.width, c.height)
        img[..., 0].sum().backward()
        assert col.grad is not None
        out.append(col.grad[:, 0].numpy().copy())
    return np.stack(out)


def capture_fits(capture: Path, every: int, work: Path) -> tuple[Any, Cameras, list[int], list[int], Any, Any]:
    """The capture's undistorted photos and cameras, its training (every `every`-th) and held-out
    indices, and its two fits under `work` (resumed): dense (every photo, 5,000 steps) and sparse
    (the training photos, 3,000 steps), the toy study's settings."""
    posed = load_posed_images(capture)
    n = len(posed)
    imgs, cam_list, _ = posed.read(list(range(n)), cache=work / "undistorted")
    train = list(range(0, n, every))
    held = [i for i in range(n) if i not in train]

    def cfg(steps: int) -> Any:
        return fit_config({"steps": steps, "random_points": 20000, "cap_max": 60000}, 0)

    dense = fit(capture, work / "dense", config=cfg(5000), views=list(range(n)), holdout="none",
                progress=False, resume=True).scene
    sparse = fit(capture, work / f"sparse-every{every}", config=cfg(3000), views=train, holdout="none",
                 progress=False, resume=True).scene
    return imgs, Cameras.from_list(cam_list), train, held, dense, sparse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", nargs="?", type=Path, default=HERE.parent / "tests/fixtures/captures/skull")
    ap.add_argument("--every", type=int, default=4, help="the sparse fit's training photos: every N-th")
    ap.add_argument("--work", type=Path, default=Path("capture-anatomy"), help="fits and the contact sheet")
    a = ap.parse_args()
    imgs, cams, train, held, dense, sparse = capture_fits(a.capture, a.every, a.work)
    n = len(cams)
    hcams = Cameras.from_list([cams[i] for i in held])
    tcams = [cams[i] for i in train]
    photo = np.stack([imgs[i] for i in held]).astype(np.float64) / 255.0
    rd = morphgs.render(dense, hcams)
    ref = np.asarray(rd.rgb, np.float64)

    def score(scene: Any) -> tuple[float, float]:
        r = np.asarray(morphgs.render(scene, hcams).rgb, np.float64)
        return (float(np.mean([psnr(r[k], photo[k]) for k in range(len(held))])),
                float(np.mean([psnr(r[k], ref[k]) for k in range(len(held))])))

    base = score(sparse)
    print(f"{a.capture.name}: {n} photos, training {train} ({len(train)}), {len(held)} held out; dense fit "
          f"{len(dense)} Gaussians, sparse {len(sparse)}")
    print(f"held-out PSNR: sparse vs photo {base[0]:.2f} dB, vs the dense render {base[1]:.2f} dB; dense vs photo "
          f"{np.mean([psnr(ref[k], photo[k]) for k in range(len(held))]):.2f} dB")
    t = in_training_views(sparse, tcams, np.asarray(morphgs.render(dense, Cameras.from_list(tcams)).depth))
    seen, rel, foot = t["seen"], t["rel"], t["foot"]
    opac = np.asarray(sparse.opacities, np.float64).reshape(-1)
    print(f"log(z / dense surface) p10/50/90 {q(rel)}; footprint px {q(foot)}; opacity {q(opac)}")
    groups = {"seen by no training view": seen == 0, "seen by 1-2": (seen >= 1) & (seen <= 2), "seen by 3+": seen >= 3,
              "in front of the surface (log z/d < -0.1)": rel < -0.1, "at it (|log z/d| <= 0.1)": np.abs(rel) <= 0.1,
              "behind it (> 0.1)": rel > 0.1, "footprint < 1 px": foot < 1, "footprint 1-3 px": (foot >= 1) & (foot < 3),
              "footprint >= 3 px": foot >= 3, "opacity < 0.2": opac < 0.2, "opacity >= 0.5": opac >= 0.5}
    wt = blend_weights(sparse, tcams)
    wh = blend_weights(sparse, list(hcams)) if wt is not None else None
    if wt is not None and wh is not None:
        groups["hidden in every training view (< 0.25 px), seen held out"] = (wt.max(0) < 0.25) & (wh.max(0) >= 0.25)
    front = rel < -0.1
    if front.any():
        cen = np.array([np.linalg.inv(np.asarray(c.world_to_camera, np.float64))[:3, 3] for c in tcams])
        spacing = float(np.median([np.min(np.delete(np.linalg.norm(cen - x, axis=1), k)) for k, x in enumerate(cen)]))
        near = np.min(np.linalg.norm(np.asarray(sparse.means, np.float64)[front][:, None] - cen[None], axis=2), axis=1)
        lum = np.asarray(sparse.colors, np.float64)[front] @ LUMA
        print(f"in front of the surface: {int(front.sum())} Gaussians, opacity {q(opac[front])}, luminance {q(lum)} "
              f"(all: {q(np.asarray(sparse.colors, np.float64) @ LUMA)}), footprint px {q(foot[front])}, "
              f"log z/d {q(rel[front])}, nearest training camera / spacing D {q(near / spacing)}")
    print("| group | Gaussians | held-out vs photo without it | vs the dense render |\n|---|---|---|---|")
    for name, m in groups.items():
        s = score(sparse.subset(np.nonzero(~m)[0]))
        print(f"| {name} | {int(m.sum())} | {s[0]:.2f} ({s[0] - base[0]:+.2f}) | {s[1]:.2f} ({s[1] - base[1]:+.2f}) |")
    flat = morphgs.GaussianScene.from_arrays(means=sparse.means, quats=sparse.quats, log_scales=sparse.log_scales,
                                             opacity_logits=sparse.opacity_logits, sh0=sparse.sh0,
                                             sh_rest=np.zeros_like(np.asarray(sparse.sh_rest)))
    s = score(flat)
    print(f"| view-dependent colour (SH 1-3) removed | all | {s[0]:.2f} ({s[0] - base[0]:+.2f}) | "
          f"{s[1]:.2f} ({s[1] - base[1]:+.2f}) |")
    # geometry or appearance: each fit's Gaussians with the other's colours (SH of the nearest
    # Gaussian of the other fit, by centre)
    from scipy.spatial import cKDTree

    def recolour(geom: Any, colours: Any) -> Any:
        _, idx = cKDTree(np.asarray(colours.means, np.float64)).query(np.asarray(geom.means, np.float64))
        return morphgs.GaussianScene.from_arrays(means=geom.means, quats=geom.quats, log_scales=geom.log_scales,
                                                 opacity_logits=geom.opacity_logits, sh0=np.asarray(colours.sh0)[idx],
                                                 sh_rest=np.asarray(colours.sh_rest)[idx])

    for name, sc in (("the sparse geometry, the dense fit's colours", recolour(sparse, dense)),
                     ("the dense geometry, the sparse fit's colours", recolour(dense, sparse))):
        s = score(sc)
        print(f"| {name} | all | {s[0]:.2f} ({s[0] - base[0]:+.2f}) | {s[1]:.2f} ({s[1] - base[1]:+.2f}) |")
    rs = morphgs.render(sparse, hcams)
    r = np.asarray(rs.rgb, np.float64)
    alpha_d = np.asarray(rd.alpha).reshape(r.shape[:3])
    alpha_s = np.asarray(rs.alpha).reshape(r.shape[:3])
    obj = alpha_d > 0.5
    res = r @ LUMA - ref @ LUMA
    e2 = res**2
    print(f"residual luminance (sparse - dense render): {e2[obj].sum() / e2.sum():.0%} of the squared error on the "
          f"object (dense alpha > 0.5, {obj.mean():.0%} of pixels), mean there {res[obj].mean():+.3f}, "
          f"{e2[obj & (res < 0)].sum() / e2[obj].sum():.0%} of it from darker pixels; object alpha dense "
          f"{alpha_d[obj].mean():.3f}, sparse {alpha_s[obj].mean():.3f}, {e2[obj & (alpha_s < 0.9)].sum() / e2[obj].sum():.0%}"
          " of the object's squared error where the sparse alpha < 0.9")
    import imageio.v3 as iio

    rows = [np.concatenate([photo[k], ref[k], r[k]], 1) for k in range(0, len(held), 3)]
    a.work.mkdir(parents=True, exist_ok=True)
    iio.imwrite(a.work / f"sheet-every{a.every}.png", (np.clip(np.concatenate(rows, 0), 0, 1) * 255).astype(np.uint8))
    print(f"contact sheet (photo | dense | sparse, every third held-out view): {a.work / f'sheet-every{a.every}.png'}")


if __name__ == "__main__":
    main()
