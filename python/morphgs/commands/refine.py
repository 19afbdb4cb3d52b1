"""`morphgs refine RUN INPUT --out OUT`: refine a clip with a trained run (docs/training.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "refine", help="refine a clip (frames folder, MP4 or curated pair) with a trained run",
        description="Refine INPUT with the model of RUN: overlapping windows blended over their overlaps, then "
                    "colour correction (Reinhard transfer in CIELAB) against --color-ref or the input clip. "
                    "Writes OUT/frames/00000.png ... (and OUT/refined.mp4 with --video). A curated pair's corrupted "
                    "frames are refined, and PSNR/SSIM against its clean frames are printed and written "
                    "to OUT/metrics.json with a before/after/target strip OUT/preview.png.")
    p.add_argument("run", metavar="RUN", help="run folder (morphgs train --out)")
    p.add_argument("input", metavar="INPUT", help="folder of frames, a video, or a curated pair folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--checkpoint", default=None, help="checkpoint folder (default: the run's latest)")
    p.add_argument("--video", action="store_true", help="also write OUT/refined.mp4")
    p.add_argument("--fps", type=float, default=16, help="video frame rate (16)")
    p.add_argument("--color-ref", default=None, help="frames (folder or video) whose colours to match")
    p.add_argument("--no-color-correct", action="store_true", help="skip the colour correction")
    p.add_argument("--reference", default=None, help="clean reference frames, for models trained with them")
    p.add_argument("--window", type=int, default=None, help="frames per model call (default: the model's)")
    p.add_argument("--overlap", type=int, default=None, help="frames shared by neighbouring windows (window/4)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 ... (default: cuda if available)")
    p.add_argument("--bf16", action="store_true", help="run the model under bf16 autocast")
    p.set_defaults(func=run)


def resolve_input(path: str | Path) -> tuple[Path, Path | None]:
    """(clip to refine, its clean frames when INPUT is a curated pair folder)."""
    p = Path(path)
    if p.is_dir():
        for name in ("corrupted", "corrupted.mp4"):
            if (p / name).exists() and (p / "cameras.json").is_file():
                clean = p / name.replace("corrupted", "clean")
                return p / name, clean if clean.exists() else None
    return p, None


def run(args: argparse.Namespace) -> int:
    from morphgs import media

    try:
        from morphgs.inference import load_run, refine_clip
    except ImportError as e:
        raise SystemExit(f"morphgs refine: error: {e}; install the training extra: pip install 'morphgs[train]'") \
            from None
    loaded = load_run(args.run, checkpoint=args.checkpoint, device=args.device)
    clip_path, clean_path = resolve_input(args.input)
    frames = media.read_clip(clip_path)
    color_ref = media.read_clip(args.color_ref) if args.color_ref else None
    reference = media.read_clip(args.reference) if args.reference else None
    refined = refine_clip(loaded.model, frames, window=args.window, overlap=args.overlap, reference=reference,
                          color_correct=not args.no_color_correct, color_reference=color_ref, device=loaded.device,
                          autocast=args.bf16)
    out = Path(args.out)
    media.write_frames(out / "frames", refined)
    print(f"{out / 'frames'}: {len(refined)} refined frames ({loaded.config.model}, {loaded.checkpoint.name})")
    if args.video:
        print(f"{media.write_video(out / 'refined.mp4', refined, fps=args.fps)}")
    if clean_path is not None:
        report = pair_report(frames, refined, media.read_clip(clean_path), out)
        print(f"vs clean: PSNR {report['psnr_input']:.2f} -> {report['psnr_refined']:.2f} dB, "
              f"SSIM {report['ssim_input']:.4f} -> {report['ssim_refined']:.4f} (input -> refined); "
              f"{out / 'preview.png'}")
    return 0


def pair_report(corrupted: Any, refined: Any, clean: Any, out: Path) -> dict[str, float]:
    """PSNR/SSIM of corrupted-vs-clean and refined-vs-clean (means over frames), written to
    OUT/metrics.json, and a before/after/target strip with them to OUT/preview.png."""
    import json

    from PIL import Image

    from morphgs.metrics import psnr, ssim
    from morphgs.training.logs import preview_strip

    report = {"frames": len(clean), "psnr_input": float(psnr(corrupted, clean)),
              "psnr_refined": float(psnr(refined, clean)), "ssim_input": float(ssim(corrupted, clean)),
              "ssim_refined": float(ssim(refined, clean))}
    (out / "metrics.json").write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    labels = [f"before: corrupted  PSNR {report['psnr_input']:.2f} dB  SSIM {report['ssim_input']:.4f}",
              f"after: refined  PSNR {report['psnr_refined']:.2f} dB  SSIM {report['ssim_refined']:.4f}",
              "target: clean"]
    Image.fromarray(preview_strip([corrupted, refined, clean], labels=labels, frames=4)).save(out / "preview.png")
    return report
