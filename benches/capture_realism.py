"""The corruption families against a real capture's sparse-view fit (docs/artifacts.md, "Veil"):
each family applied to the capture's dense fit with the sparse fit's own training photos as the
virtual training cameras, its strength bisected to the real sparse fit's held-out PSNR against
the dense fit's renders, and told from the real held-out frames by the CNN two-sample test.

    python benches/capture_realism.py                                # the committed skull, every 4th photo
    python benches/capture_realism.py CAPTURE --every 3 --family veil --family shatter --work /tmp/anatomy

The fits are benches/capture_anatomy.py's (a dense fit of every photo, 5,000 steps; a sparse fit
of every `--every`-th, 3,000 steps; resumed from the same --work). Real pairs: the sparse fit's
render of each held-out photo's camera against the dense fit's. Synthetic pairs: the family's
render against the same. Printed per family: the matched strength, the held-out PSNR, the
training views' PSNR (a real sparse fit keeps its own photos), the share of the squared error on
the object (dense alpha > 0.5) and from darker pixels, and the classifier's cross-fitted AUC and
d' on one-frame clips (each held-out view a clip; `--seeds` op seeds, one synthetic clip per view
and seed, as many real clips repeated). Reports; asserts nothing. Needs torch (`morphgs[metrics]`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import morphgs
from morphgs.calibration.realism import Clip, classifier_test
from morphgs.camera import Cameras
from morphgs.strength import Strength

sys.path.insert(0, str(Path(__file__).resolve().parent))
from capture_anatomy import capture_fits  # noqa: E402  (the same fits, resumed from the same --work)

HERE = Path(__file__).resolve().parent
LUMA = np.array([0.299, 0.587, 0.114])


def mean_psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((np.clip(a, 0, 1) - b) ** 2, axis=(1, 2, 3))
    return float(np.mean(10 * np.log10(1.0 / np.maximum(mse, 1e-12))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", nargs="?", type=Path, default=HERE.parent / "tests/fixtures/captures/skull")
    ap.add_argument("--every", type=int, default=4, help="the sparse fit's training photos: every N-th")
    ap.add_argument("--work", type=Path, default=Path("capture-anatomy"), help="the fits (capture_anatomy.py's)")
    ap.add_argument("--family", action="append", help="a strength family or a JSON file {\"family\": ..., "
                    "\"ops\": {op: base value}} (repeatable; default: shatter, morphological, haze, veil)")
    ap.add_argument("--seeds", type=int, default=2, help="op seeds per family (synthetic clips per view)")
    ap.add_argument("--steps", type=int, default=240, help="the classifier's training steps")
    ap.add_argument("--repeats", type=int, default=1, help="networks per fold, their logits averaged")
    ap.add_argument("--sheet", type=Path, help="write a contact sheet here: per row a held-out view (every "
                    "fourth), the dense render, the real sparse fit's, then each family's (first seed)")
    a = ap.parse_args()
    families = a.family or ["shatter", "morphological", "haze", "veil"]
    _, cams, train, held, dense, sparse = capture_fits(a.capture, a.every, a.work)
    hcams = Cameras.from_list([cams[i] for i in held])
    tcams = Cameras.from_list([cams[i] for i in train])
    rd = morphgs.render(dense, hcams)
    ref = np.asarray(rd.rgb, np.float64)
    tref = np.asarray(morphgs.render(dense, tcams).rgb, np.float64)
    obj = np.asarray(rd.alpha).reshape(ref.shape[:3]) > 0.5

    def anatomy(r: np.ndarray) -> tuple[float, float, float]:
        res = r @ LUMA - ref @ LUMA
        e2 = res**2
        return (float(e2[obj].sum() / e2.sum()), float(e2[obj & (res < 0)].sum() / max(e2[obj].sum(), 1e-12)),
                float(res[obj].mean()))

    real = np.asarray(morphgs.render(sparse, hcams).rgb, np.float64)
    target = mean_psnr(real, ref)
    on, dark, mean = anatomy(real)
    train_real = mean_psnr(np.asarray(morphgs.render(sparse, tcams).rgb, np.float64), tref)
    print(f"{a.capture.name}, every {a.every}th photo ({len(train)} training, {len(held)} held out): real sparse fit "
          f"held out {target:.2f} dB against the dense render, training views {train_real:.2f} dB; "
          f"{on:.0%} of the error on the object, {dark:.0%} of it darker (mean {mean:+.3f})")
    print("| family | strength | held out | training views | on the object | darker (mean) | AUC | d' | seconds |")
    print("|---|---|---|---|---|---|---|---|---|")

    def render_at(fam: Strength, s: float, seed: int, cams_: Cameras) -> np.ndarray:
        out = fam.at(s).apply(dense, seed=seed, train_cameras=tcams)
        return np.asarray(morphgs.render(out, cams_).rgb, np.float64)

    columns, shown = [ref, real], []
    for name in families:
        t0 = time.perf_counter()
        fam = (Strength.from_dict(json.loads(Path(name).read_text())) if name.endswith(".json")
               else Strength(name))
        lo, hi = math.log(0.01), math.log(64.0)
        if mean_psnr(render_at(fam, math.exp(hi), a.seeds, hcams), ref) > target:
            print(f"| {name} | unreachable (64: {mean_psnr(render_at(fam, 64.0, a.seeds, hcams), ref):.1f} dB) "
                  "| | | | | | | |")
            continue
        for _ in range(14):  # bisect log s on the first seed's held-out PSNR
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if mean_psnr(render_at(fam, math.exp(mid), 0, hcams), ref) > target else (lo, mid)
        s = math.exp(0.5 * (lo + hi))
        synth = [render_at(fam, s, seed, hcams) for seed in range(a.seeds)]
        got = float(np.mean([mean_psnr(x, ref) for x in synth]))
        tr = float(np.mean([mean_psnr(render_at(fam, s, seed, tcams), tref) for seed in range(a.seeds)]))
        on, dark, mean = anatomy(synth[0])
        columns.append(synth[0])
        shown.append(Path(name).stem)
        clips = [Clip(real[k][None].astype(np.float32), ref[k][None].astype(np.float32), f"v{k}", 0)
                 for _ in range(a.seeds) for k in range(len(held))]
        clips += [Clip(x[k][None].astype(np.float32), ref[k][None].astype(np.float32), f"v{k}", 1)
                  for x in synth for k in range(len(held))]
        res = classifier_test(clips, seed=0, steps=a.steps, repeats=a.repeats)
        print(f"| {name} | {s:.3g} | {got:.2f} | {tr:.2f} | {on:.0%} | {dark:.0%} ({mean:+.3f}) | {res['auc']:.2f} | "
              f"{res['separation']:.1f} | {time.perf_counter() - t0:.0f} |", flush=True)

    if a.sheet:
        import imageio.v3 as iio

        rows = [np.concatenate([c[k] for c in columns], 1) for k in range(0, len(held), 4)]
        a.sheet.parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(a.sheet, (np.clip(np.concatenate(rows, 0), 0, 1) * 255).astype(np.uint8))
        print(f"contact sheet (dense | real sparse | {' | '.join(shown)}): {a.sheet}")


if __name__ == "__main__":
    main()
