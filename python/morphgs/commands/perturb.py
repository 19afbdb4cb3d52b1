"""`morphgs perturb IN OUT --preset morphological --seed 7`: write a perturbed copy of a scene.

Also `--preset FAMILY~S` (a family of the strength parameterisation at strength S) and `--config
FILE` holding a strength config ({"kind": "strength", ...}, e.g. from `morphgs calibrate`; a
strength distribution draws the strength from the seed, as curate does). Popping is per-frame
visibility: the written PLY carries its caps as the properties popping_x/y/z/h, which morphgs's
renderer honours (docs/artifacts.md)."""

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
        default="morphological",
        metavar="NAME",
        help=f"the starting configuration: {', '.join(PRESETS)}, or FAMILY~S, a family of the strength "
        "parameterisation at strength S (e.g. morphological~2; docs/perturbation.md) (default: morphological)",
    )
    src.add_argument(
        "--config",
        metavar="FILE",
        help="start from a JSON config (as PerturbConfig.to_json writes), or a strength config "
        '{"kind": "strength", "family", "strength" | "quantiles", "ops"} as morphgs calibrate writes '
        "(a strength distribution draws the strength from --seed, as curate does)",
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


def _strength_config(args: argparse.Namespace) -> dict[str, Any] | None:
    """The strength config of `--preset FAMILY~S` or of a strength `--config` file; None for the
    PerturbConfig forms.

    Raises:
        ValueError: an unreadable or invalid file, a bad FAMILY~S, or options that do not apply to
            a strength config (naming them).
    """
    from morphgs.curation.plan import parse_config

    if args.config:
        path = Path(args.config)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"--config {path}: cannot read JSON ({e})") from None
        if not isinstance(data, dict):
            raise ValueError(f"--config {path}: expected a JSON object")
        if data.get("kind") == "blur2d":
            raise ValueError(f"--config {path}: blur2d blurs rendered frames, not a scene; use it with morphgs curate")
        if data.get("kind") != "strength":
            return None
        if path.suffix.lower() != ".json":
            raise ValueError(f"--config {path}: a strength config file must end in .json")
        spec = str(path)
    elif "~" in args.preset:
        spec = args.preset
    else:
        return None
    try:
        params = parse_config(spec).params
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if args.config else msg.replace("--config", "--preset", 1)) from None
    flags = [f"--{_flag(f)}" for f in FIELDS if getattr(args, f) is not None]
    flags += [f"--no-{_flag(f)}" for f in FIELDS if getattr(args, f"no_{f}")]
    if args.strength is not None:
        flags.append("--strength")
    if flags:
        raise ValueError(f"{', '.join(flags)} set PerturbConfig fields and do not apply to the strength config "
                         f"{spec}; give the strength in FAMILY~S or in the file")
    return {"kind": "strength", **params}


def config_from_args(args: argparse.Namespace) -> PerturbConfig:
    """The config the arguments describe: preset or file, then per-field overrides, then strength.

    Raises:
        ValueError: conflicting or invalid values (the message names the option).
    """
    if args.config:
        cfg = PerturbConfig.from_json(Path(args.config).read_text())
    else:
        if args.preset not in PRESETS:
            raise ValueError(f"--preset {args.preset}: expected one of {', '.join(PRESETS)} or FAMILY~STRENGTH")
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
        if args.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {args.seed}")
        strength = _strength_config(args)
        cfg = config_from_args(args) if strength is None else None
    except ValueError as e:
        print(f"morphgs perturb: error: {e}", file=sys.stderr)
        return 2
    scene = morphgs.load(args.input)
    if strength is not None:
        from morphgs.strength import from_config

        st = from_config(strength, args.seed)
        cams = None
        if st.needs_cameras:  # the sparse-view ops' training views: every K-th of an orbit of 8 K views
            from morphgs import trajectory

            cams = trajectory.for_scene(scene, 8 * st.train_every, resolution=(256, 192))
        out, mask = st.apply(scene, seed=args.seed, return_mask=True, cameras=cams)
        extra: dict[str, Any] = {"strength": st.strength, "config": st.to_dict()}
        if "popping_h" in out.extras:  # per-frame visibility: its caps ride along in the PLY
            extra["popping"] = int(np.count_nonzero(out.extras["popping_h"]))
        if cams is not None:
            extra["training_cameras"] = f"every {st.train_every}th of an orbit of {len(cams)} views at 256x192"
        drawn = " (drawn from its quantile table)" if "quantiles" in strength else ""
        label = f" (family {st.family}, strength {st.strength:.6g}{drawn})"
        ops = ", ".join(f"{k} {v:.6g}" for k, v in st.values().items())
        config_text = json.dumps(st.to_dict())
    else:
        assert cfg is not None
        out, mask = morphgs.perturb(scene, cfg, seed=args.seed, return_mask=True)
        extra = {"config": cfg.to_dict()}
        label = f" (preset {cfg.name})" if cfg.name else ""
        ops = ", ".join(cfg.enabled)
        config_text = cfg.to_json()
    morphgs.save_ply(out, args.output)
    if args.mask:
        np.save(args.mask, mask)
    kept = int(np.count_nonzero(mask[:len(scene)]))  # the mask's rows past the input's: added Gaussians
    summary = {"input": str(args.input), "output": str(args.output), "seed": args.seed, "gaussians_in": len(scene),
               "kept": kept, "pruned": len(scene) - kept, "spawned": len(mask) - len(scene), **extra}
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"perturbed {args.input} -> {args.output}{label}, seed {args.seed}")
    spawned = f", {summary['spawned']:,} added (floaters, shatter fragments, haze, veil)" if summary["spawned"] else ""
    print(f"  gaussians : {len(scene):,} in, {kept:,} kept, {len(scene) - kept:,} pruned{spawned}")
    print(f"  operations: {ops or 'none'}")
    if "popping" in summary:
        print(f"  popping   : {summary['popping']:,} Gaussians pop (their caps are the PLY properties popping_x, "
              "popping_y, popping_z, popping_h; morphgs renders them frame by frame, other renderers ignore them)")
    print(f"  config    : {config_text}")
    return 0
