"""What a study's real sparse fits hold near the capture path, and how much of their error it is
(docs/artifacts.md, "Haze"): for each test set of a `morphgs ablate` study folder (its sparse fit,
its capture's cameras, its novel-view test clips), the Gaussians within half a training-camera
spacing D of the capture path and wider than 0.03 D (largest scale): their count and statistics,
and the clips' PSNR against the clean renders with and without them (and the training views'
change). The `haze` op's constants (`morphgs.haze`) come from these figures. Reports; asserts
nothing.

    python benches/haze_anatomy.py STUDY            # e.g. the folder of morphgs ablate --preset toy
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import morphgs
from morphgs import media
from morphgs.ablation.stages.captures import load_cameras
from morphgs.camera import Cameras
from morphgs.haze import spacing


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / max(np.mean((a.astype(np.float64) - b) ** 2), 1e-12)))


def q(a: np.ndarray, ps: tuple[float, ...] = (0.25, 0.5, 0.75)) -> str:
    return " / ".join(f"{v:.3g}" for v in np.quantile(a, ps)) if len(a) else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("study", type=Path, help="a morphgs ablate output folder (testsets/, captures/)")
    args = ap.parse_args()
    sets = sorted(p for p in (args.study / "testsets").iterdir() if (p / "testset.json").is_file())
    if not sets:
        raise SystemExit(f"{args.study}: no finished test sets under testsets/")
    print("test set | D | near-path wide (of all) | opacity q1/med/q3 | largest scale / D | "
          "nearest training camera / D | luminance | clips PSNR: fit / without them | training views change")
    rows = []
    for ts in sets:
        meta = json.loads((ts / "testset.json").read_text(encoding="utf-8"))
        fit = sorted((ts / "fit" / "point_cloud").glob("iteration_*/point_cloud.ply"))[-1]
        scene = morphgs.load(fit)
        cap = next((args.study / "captures").glob(f"{meta['scene']}-*"))
        cams = load_cameras(cap)
        centers = np.array([np.linalg.inv(np.asarray(c.world_to_camera))[:3, 3] for c in cams])
        tv = meta["train_views"]
        D = spacing(centers[tv])
        means = np.asarray(scene.means, np.float64)
        largest = np.asarray(scene.scales, np.float64).max(axis=1)
        d_path = np.min(np.linalg.norm(means[:, None] - centers[None], axis=2), axis=1)
        d_train = np.min(np.linalg.norm(means[:, None] - centers[tv][None], axis=2), axis=1)
        wide = (d_path < 0.5 * D) & (largest > 0.03 * D)
        rest = np.nonzero(~wide)[0]
        opacity = np.asarray(scene.opacities)[wide]
        lum = np.asarray(scene.colors)[wide].mean(axis=1)
        with_, without = [], []
        for j in meta["clips"]:
            cc = Cameras.from_dict(json.loads((ts / "clips" / j / "cameras.json").read_text(encoding="utf-8")))
            clean = media.read_clip(ts / "clips" / j / "clean")
            with_.append(psnr(media.read_clip(ts / "clips" / j / "corrupted"), clean))
            without.append(psnr(morphgs.render(scene.subset(rest), cc).to_uint8(), clean))
        tc = Cameras.from_list([cams[i] for i in tv])
        change = psnr(morphgs.render(scene.subset(rest), tc).to_uint8(), morphgs.render(scene, tc).to_uint8())
        rows.append((np.mean(with_), np.mean(without)))
        print(f"{ts.name.rsplit('-', 1)[0]} | {D:.2f} | {wide.sum()} ({len(means)}) | {q(opacity)} | "
              f"{q(largest[wide] / D)} | {q(d_train[wide] / D)} | {q(lum)} | {np.mean(with_):.2f} / "
              f"{np.mean(without):.2f} dB | {change:.1f} dB")
    r = np.array(rows)
    print(f"mean over {len(rows)} test sets: clips {r[:, 0].mean():.2f} dB with them, {r[:, 1].mean():.2f} dB without")


if __name__ == "__main__":
    main()
