"""`morphgs perturb IN OUT --preset morphological --seed 7`: write a perturbed copy of a scene."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

import morphgs
from morphgs.perturb import FIELDS, PRESETS, PerturbConfig


def _flag(field: str) -> str:
    return field.replace("_", "-")


def register(sub: Any) -> None:
    p = sub.add_parser(
        "perturb",
        help="perturb a scene's Gaussians (the paper's spatial/radiometric/morphological noise)",
        description="Load a scene, perturb it with a preset (optionally overriding single "
        "operations) and write the result as an INRIA PLY.",
    )
    p.add_argument("input", help="the clean scene file")
    p.add_argument("output", help="the PLY file to write")
    p.add_argument("--seed", type=int, required=True, help="the random seed (an int >= 0)")
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--preset",
        choices=PRESETS,
        default="morphological",
        help="the starting configuration (default: morphological)",
    )
    src.add_argument(
        "--config", metavar="FILE", help="start from a JSON config (as PerturbConfig.to_json writes)"
    )
    for field in FIELDS:
        what = "probability" if field == "prune" else "noise scale"
        p.add_argument(f"--{_flag(field)}", type=float, metavar="X", help=f"set the {field} {what}")
        p.add_argument(
            f"--no-{_flag(field)}", action="store_true", help=f"disable {field.replace('_', ' ')}"
        )
    p.add_argument(
        "--strength", type=float, metavar="K", help="multiply every noise scale by K (see PerturbConfig.scaled)"
    )
    p.add_argument("--mask", metavar="FILE", help="also save the keep-mask as a .npy file")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> PerturbConfig:
    """The config the arguments describe: preset or file, then per-field overrides, then strength.

    Raises:
        ValueError: conflicting or invalid values (the message names the option).
    """
    if args.config:
        cfg = PerturbConfig.from_json(Path(args.config).read_text())
    else:
        cfg = PerturbConfig.preset(args.preset)
    changes: dict[str, float | None] = {}
    for field in FIELDS:
        value = getattr(args, field)
        off = getattr(args, f"no_{field}")
        if value is not None and off:
            raise ValueError(f"--{_flag(field)} and --no-{_flag(field)} contradict each other")
        if off:
            changes[field] = None
        elif value is not None:
            changes[field] = value
    if changes:
        cfg = dataclasses.replace(cfg, **changes, name=None)
    if args.strength is not None:
        cfg = cfg.scaled(args.strength)
    return cfg


def run(args: argparse.Namespace) -> int:
    try:
        cfg = config_from_args(args)
        if args.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {args.seed}")
    except ValueError as e:
        print(f"morphgs perturb: error: {e}", file=sys.stderr)
        return 2
    scene = morphgs.load(args.input)
    out, mask = morphgs.perturb(scene, cfg, seed=args.seed, return_mask=True)
    morphgs.save_ply(out, args.output)
    if args.mask:
        np.save(args.mask, mask)
    summary = {
        "input": str(args.input),
        "output": str(args.output),
        "seed": args.seed,
        "gaussians_in": len(scene),
        "kept": len(out),
        "pruned": len(scene) - len(out),
        "config": cfg.to_dict(),
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    label = f" (preset {cfg.name})" if cfg.name else ""
    print(f"perturbed {args.input} -> {args.output}{label}, seed {args.seed}")
    print(f"  gaussians : {len(scene):,} in, {len(out):,} kept, {len(scene) - len(out):,} pruned")
    print(f"  operations: {', '.join(cfg.enabled) or 'none'}")
    print(f"  config    : {cfg.to_json()}")
    return 0
