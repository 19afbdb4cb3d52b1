"""What a real sparse-view fit is made of, and how close a strength family's pairs come to its pairs
(docs/artifacts.md, "What a sparse fit is made of").

    python benches/sparse_anatomy.py CALIB            # CALIB: a `morphgs calibrate --regime sparse:K` output
    python benches/sparse_anatomy.py CALIB --family shatter --strengths 2,4,8

Part 1, per fit under CALIB/real/fits: for each Gaussian, the nearest training view whose frustum
holds it and the clean depth d at its pixel there: log(z / d) percentiles, the share within 10 %
of the surface, its footprint (pixels) and opacity percentiles, and the PSNR of the fit's
training views against the clean renders. Part 2: the family's synthetic pairs on (every third
of) the real pairs' cameras and seeds, with the real fit's training views, at each strength:
median PSNR and error-to-signal power per frequency band, beside the real pairs'.

Needs the built-in scenes' sources (as calibrate made them) or the SCENE paths calibrate was given.
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import numpy as np


def anatomy(calib: Path) -> None:
    import morphgs
    from morphgs.calibration.pairs import read_real_pairs
    from morphgs.calibration.run import find_scenes
    from morphgs.rendering import render_many

    pairs = read_real_pairs(calib / "real")
    scenes = {s.id: s for s in find_scenes([])}
    seen: set[str] = set()
    for p in pairs:
        if p.scene in seen or p.train_cameras is None or p.scene not in scenes:
            continue
        seen.add(p.scene)
        rec = next(json.loads(line) for f in sorted((calib / "real").glob("manifest*.jsonl"))
                   for line in f.read_text().splitlines() if json.loads(line)["pair_id"] == p.pair_id)
        fit = morphgs.load(str(calib / "real" / rec["fit"]["ply"]))
        clean = scenes[p.scene].load()
        tr = p.train_cameras
        r = render_many([clean], tr)[0]
        dep = np.asarray(r.depth)
        mu = np.asarray(fit.means, np.float64)
        ratio = np.full(len(mu), np.nan)
        foot = np.full(len(mu), np.nan)
        nearest = np.full(len(mu), np.inf)
        for t in range(len(tr)):
            m, k = tr.world_to_camera[t], tr.K[t]
            c = mu @ m[:3, :3].T + m[:3, 3]
            z = c[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = k[0, 0] * c[:, 0] / z + k[0, 2], k[1, 1] * c[:, 1] / z + k[1, 2]
            ok = (z > 0.05) & (u >= 0) & (u < tr.width) & (v >= 0) & (v < tr.height) & (z < nearest)
            surf = dep[t][v[ok].astype(int), u[ok].astype(int)]
            nearest[ok] = z[ok]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio[ok] = np.log(z[ok] / surf)
            foot[ok] = np.asarray(fit.scales).max(1)[ok] * k[0, 0] / z[ok]
        lr = ratio[np.isfinite(ratio)]
        fit_train = render_many([fit], tr)[0].rgb
        psnr = -10 * np.log10(np.mean((np.clip(fit_train, 0, 1) - np.clip(r.rgb, 0, 1)) ** 2, axis=(1, 2, 3)))
        print(f"{p.scene}: {len(fit)} Gaussians; log(z/d) 5/25/50/75/95 % {np.percentile(lr, [5, 25, 50, 75, 95]).round(2)}; "
              f"within 10 % of the surface {np.mean(np.abs(lr) < 0.1):.2f}; footprint px 5/50/95 % "
              f"{np.percentile(foot[np.isfinite(foot)], [5, 50, 95]).round(2)}; opacity 5/50/95 % "
              f"{np.percentile(fit.opacities, [5, 50, 95]).round(3)}; training views {psnr.round(1)} dB")


def compare(calib: Path, family: str, strengths: list[float], every: int) -> None:
    from morphgs.calibration import stats
    from morphgs.calibration.pairs import Bench, read_real_pairs
    from morphgs.calibration.run import find_scenes, load_scenes
    from morphgs.strength import Strength

    pairs = read_real_pairs(calib / "real")[::every]
    bench = Bench(load_scenes(find_scenes([]), {"r": pairs}), pairs)
    cfg = Strength.from_dict(json.loads(Path(family).read_text())) if family.endswith(".json") else Strength(family)
    real = [stats.pair_stats(p.corrupted, bench.clean[i]) for i, p in enumerate(pairs)]

    def summary(st: list[dict]) -> tuple[float, np.ndarray]:
        return (float(np.median(np.concatenate([s["frame_psnr"] for s in st]))),
                np.nanmean([[s[n] for n in stats.SPECTRUM_NAMES] for s in st], axis=0))

    rp, rs = summary(real)
    print(f"real: median PSNR {rp:.2f} dB, spectrum {np.round(rs, 1)} dB")
    for s in strengths:
        syn = [stats.pair_stats(bench.corrupted(cfg.at(s), i), bench.clean[i]) for i in range(len(pairs))]
        sp, ss = summary(syn)
        print(f"{family}~{s:g}: median PSNR {sp:.2f} dB, spectrum {np.round(ss, 1)} dB (largest gap "
              f"{np.max(np.abs(ss - rs)):.1f} dB)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calib", type=Path)
    ap.add_argument("--family", default=None, help="a strength family or a JSON config to compare (part 2)")
    ap.add_argument("--strengths", default="2,4,8")
    ap.add_argument("--every", type=int, default=3, help="compare on every N-th real pair (3)")
    a = ap.parse_args()
    if not glob.glob(str(a.calib / "real" / "manifest*.jsonl")):
        raise SystemExit(f"{a.calib}: no real pairs (run morphgs calibrate --regime sparse:K --out {a.calib} first)")
    anatomy(a.calib)
    if a.family:
        compare(a.calib, a.family, [float(x) for x in a.strengths.split(",")], a.every)


if __name__ == "__main__":
    main()
