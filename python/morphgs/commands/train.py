"""`morphgs train --data DIR --model tiny --out RUN [--config run.toml] [--resume]` (docs/training.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from morphgs.reliability import add_wait_argument


def _size(text: str) -> list[int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 128x192 (HxW), got {text!r}") from None
    return [h, w]


# flag -> (section, key)
_SHORTHANDS = {
    "max_steps": ("optim", "max_steps"),
    "lr": ("optim", "lr"),
    "grad_accum": ("optim", "grad_accum"),
    "batch_size": ("data", "batch_size"),
    "frames": ("data", "frames"),
    "size": ("data", "size"),
    "workers": ("data", "num_workers"),
    "mixed_precision": ("run", "mixed_precision"),
    "time_limit": ("run", "time_limit"),
    "checkpoint_every": ("run", "checkpoint_every"),
    "validate_every": ("run", "validate_every"),
}


def register(sub: Any) -> None:
    p = sub.add_parser(
        "train", help="train a refiner on a curated folder (torch: pip install 'morphgs[train]')",
        description="Train a video refiner on clean/corrupted pairs. The run folder gets the config as written, "
                    "run.json (resolved config), checkpoints/, logs/ (CSV, TensorBoard) and previews/. "
                    "`accelerate launch -m morphgs train ...` runs it on several GPUs or machines.")
    p.add_argument("--data", default=None, help="curated folder (morphgs curate output); its test split validates")
    p.add_argument("--model", default=None, help="registered model (default: the config's, else tiny)")
    p.add_argument("--out", default=None, help="run folder (required unless --list-models)")
    p.add_argument("--config", default=None, help="run config TOML (missing keys: the model's shipped config)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one config key, e.g. --set optim.lr=1e-3 (repeatable)")
    p.add_argument("--live", nargs="*", default=None, metavar="SCENE",
                   help="render pairs live from these scenes (none: the built-in scenes) instead of reading --data")
    p.add_argument("--max-steps", type=int, default=None, help="optimizer steps")
    p.add_argument("--lr", type=float, default=None, help="learning rate")
    p.add_argument("--grad-accum", type=int, default=None, help="micro-batches per optimizer step")
    p.add_argument("--batch-size", type=int, default=None, help="clips per process per micro-batch")
    p.add_argument("--frames", type=int, default=None, help="frames per clip")
    p.add_argument("--size", type=_size, default=None, help="crop HxW, e.g. 128x192")
    p.add_argument("--workers", type=int, default=None, help="DataLoader workers")
    p.add_argument("--mixed-precision", choices=("auto", "no", "bf16", "fp16"), default=None)
    p.add_argument("--time-limit", type=float, default=None, help="minutes; stop with a checkpoint after this long")
    p.add_argument("--checkpoint-every", type=int, default=None, help="steps between checkpoints")
    p.add_argument("--validate-every", type=int, default=None, help="steps between validations")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--list-models", action="store_true", help="list the registered models and exit")
    add_wait_argument(p)
    p.set_defaults(func=run)


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """--set items, then the shorthand flags, as a nested override dict."""
    from morphgs.configfile import merge, parse_overrides

    out = parse_overrides(args.set)
    flags: dict[str, Any] = {}
    for attr, (section, key) in _SHORTHANDS.items():
        value = getattr(args, attr)
        if value is not None:
            flags.setdefault(section, {})[key] = value
    if args.live is not None:
        flags.setdefault("data", {})["live"] = True
    return merge(out, flags)


def run(args: argparse.Namespace) -> int:
    if args.list_models:
        from morphgs.models import get_model, list_models

        for name in list_models():
            try:
                print(f"{name:12s} {get_model(name).description}")
            except Exception as e:  # a model whose module or extra is missing here
                print(f"{name:12s} (unavailable: {e})")
        return 0
    if args.out is None:
        raise SystemExit("morphgs train: error: --out RUN is required")
    try:
        from morphgs.training import train
    except ImportError as e:
        raise SystemExit(f"morphgs train: error: {e}; install the training extra: pip install 'morphgs[train]'") from None
    result = train(args.data, out=args.out, model=args.model, config=args.config, overrides=overrides_from_args(args),
                   resume=args.resume, scenes=args.live or (), progress=not args.no_progress, wait=args.wait)
    if result.validation:
        v = result.validation
        print(f"validation at step {result.steps}: PSNR {v['psnr_input']:.2f} -> {v['psnr_output']:.2f} dB, "
              f"SSIM {v['ssim_input']:.4f} -> {v['ssim_output']:.4f} (input -> refined, vs clean)")
    skipped = f", {result.bad_pairs} unreadable pair(s) skipped (bad_pairs.jsonl)" if result.bad_pairs else ""
    print(f"{result.run_dir}: {result.steps} steps, checkpoint {result.checkpoint}{skipped}")
    if result.preempted:
        print(f"morphgs train: stopped by {result.preempted} at step {result.steps} with a checkpoint; rerun with "
              f"--out {result.run_dir} --resume to continue", file=sys.stderr)
        return 143 if result.preempted == "SIGTERM" else 130
    return 0
