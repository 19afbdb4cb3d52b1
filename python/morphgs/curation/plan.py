"""The curation plan: configs, seeds, splits, sharding and the camera path of each pair.

Seeds and splits are pure functions of names and numbers (SHA-256 of a fixed text), so they do
not depend on the order of the inputs, the number of workers or shards, or the machine:

    pair_seed = uint64_le(sha256("morphgs/pair-seed/v1\\0{run_seed}\\0{scene_id}\\0{pair_index}")[:8]) >> 1
    split     = "test" if uint64_le(sha256("morphgs/split/v1\\0{split_seed}\\0{scene_id}")[:8]) / 2^64
                < test_fraction else "train"

(the pair seed keeps 63 bits so it fits every signed or unsigned 64-bit consumer). Every config
of a run uses the same pair seed, so an ablation compares configs on identical paths and noise
streams.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from morphgs.camera import Cameras
from morphgs.curation.sources import SceneSource

__all__ = ["FIT_KINDS", "ConfigSpec", "PairJob", "TrajectoryOptions", "check_up", "job_cameras", "job_up", "up_rule", "make_plan",
           "pair_seed", "parse_config", "scene_split"]

PRESETS = ("spatial", "radiometric", "morphological", "naive")
#: Config kinds whose corrupted side is a real 3DGS fit (morphgs.curation.sparse): every K-th view
#: or N views (`sparse`), all views stopped early (`underfit`), one part of the path (`cross`).
FIT_KINDS = ("sparse", "underfit", "cross")
#: The fit length of a fit config without steps: the `sparse` fit preset's.
DEFAULT_FIT_STEPS = 3000


def _u64(text: str) -> int:
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")


def pair_seed(run_seed: int, scene_id: str, pair_index: int) -> int:
    """The perturbation seed of pair `pair_index` of `scene_id` in a run seeded `run_seed`."""
    return _u64(f"morphgs/pair-seed/v1\0{int(run_seed)}\0{scene_id}\0{int(pair_index)}") >> 1


def scene_split(scene_id: str, *, test_fraction: float, split_seed: int = 0) -> str:
    """"train" or "test" for a scene: deterministic in (split_seed, scene_id)."""
    if not 0.0 <= test_fraction <= 1.0:
        raise ValueError(f"test_fraction must be in [0, 1], got {test_fraction}")
    u = _u64(f"morphgs/split/v1\0{int(split_seed)}\0{scene_id}") / 2.0**64
    return "test" if u < test_fraction else "train"


@dataclass(frozen=True)
class ConfigSpec:
    """One corruption of a run: a label (used in paths) and its parameters as a dict.

    kind "perturb" carries `PerturbConfig.to_dict()` in `params`; kind "strength" carries
    `Strength.to_dict()` without "kind" (a fixed "strength", or a "quantiles" table of a strength
    distribution each pair draws from, see morphgs.strength); kind "blur2d" carries
    {"sigma": pixels} or {"quantiles": a sigma distribution}; kind "sparse" carries {"every": K} or {"n": N}, optionally "steps" and
    "fit" (FitConfig overrides), see morphgs.curation.sparse; kinds "underfit" and "cross" carry
    {"fraction": F} with the same optional "steps" and "fit" (`FIT_KINDS`).
    """

    label: str
    kind: str
    params: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.label, "kind": self.kind, **self.params}

    def perturb_config(self) -> Any:
        import morphgs

        return morphgs.PerturbConfig.from_dict(self.params)


def _sparse(spec: str, label_prefix: str, key: str, body: str) -> ConfigSpec:
    count, _, steps = body.partition("@")
    try:
        k = int(count)
        st = int(steps) if steps else None
    except ValueError:
        raise ValueError(f"--config {spec!r}: expected {label_prefix}:N or {label_prefix}:N@STEPS with integers") from None
    if k < 1 or (st is not None and st < 1):
        raise ValueError(f"--config {spec!r}: the view count and the steps must be >= 1")
    params: dict[str, Any] = {key: k}
    label = f"{label_prefix.replace(':', '')}-{k}" if key == "every" else f"sparse-n{k}"
    if st is not None:
        params["steps"] = st
        label += f"-{st}steps"
    return ConfigSpec(label, "sparse", params)


def fit_steps(params: dict[str, Any]) -> int:
    """The full schedule length of a fit config's params: "steps", else the "fit" overrides'
    steps, else the `sparse` fit preset's (`DEFAULT_FIT_STEPS`)."""
    if "steps" in params:
        return int(params["steps"])
    fit = params.get("fit") or {}
    return int(fit["steps"]) if isinstance(fit.get("steps"), int) else DEFAULT_FIT_STEPS


def stop_step(fraction: float, steps: int) -> int:
    """The step an `underfit` fit stops at: round(fraction x steps) of the full schedule."""
    return int(round(float(fraction) * int(steps)))


def _fraction_params(kind: str, fraction: Any, steps: Any, fit: Any, where: str,
                     shown: str | None = None) -> dict[str, Any]:
    """Validated params of an underfit / cross config (`where`: how the error names the config;
    `shown`: the fraction as the user wrote it)."""
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not math.isfinite(fraction) \
            or not 0.0 < float(fraction) < 1.0:
        raise ValueError(f"{where}: 'fraction' must be a number strictly between 0 and 1, got "
                         f"{shown if shown is not None else repr(fraction)}")
    params: dict[str, Any] = {"fraction": float(fraction)}
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"{where}: 'steps' must be an integer >= 1, got {steps!r}")
        params["steps"] = steps
    if fit is not None:
        if not isinstance(fit, dict):
            raise ValueError(f"{where}: 'fit' must be an object of fit settings")
        params["fit"] = fit
    if kind == "underfit":
        n = fit_steps(params)
        if stop_step(params["fraction"], n) < 1:
            raise ValueError(f"{where}: 'fraction' {fraction} of {n} steps stops before the first step")
    return params


def _fraction_config(spec: str, kind: str, body: str) -> ConfigSpec:
    """`underfit:F[@STEPS]` / `cross:P[@STEPS]`."""
    value, _, steps = body.partition("@")
    where = f"--config {spec!r}"
    letter = "F" if kind == "underfit" else "P"
    try:
        f = float(value)
    except ValueError:
        raise ValueError(f"{where}: 'fraction' must be a number strictly between 0 and 1 "
                         f"({kind}:{letter} or {kind}:{letter}@STEPS), got {value!r}") from None
    try:
        st = int(steps) if steps else None
    except ValueError:
        raise ValueError(f"{where}: 'steps' after '@' must be an integer >= 1, got {steps!r}") from None
    params = _fraction_params(kind, f, st, None, where, shown=value)
    label = f"{kind}-{params['fraction']:g}" + (f"-{st}steps" if st is not None else "")
    return ConfigSpec(label, kind, params)


def parse_config(spec: str, *, blur_sigma: float = 2.0) -> ConfigSpec:
    """Parse a --config value.

    Forms: a preset name (spatial, radiometric, morphological, naive); `NAME@S`, the preset with
    every intensity scaled by S (`PerturbConfig.scaled`); `blur2d` or `blur2d@SIGMA` (the 2D
    baseline, sigma in pixels, default `blur_sigma`); `NAME~S`, the family NAME at strength S of
    the smooth, scene-aware strength parameterisation (`morphgs.strength.Strength`); `sparse:K` (a reconstruction from every
    K-th recorded view, the paper's S_K) or `sparse-n:N` (from N views spread evenly),
    `underfit:F` (a fit from all views stopped at the fraction F of its schedule) or `cross:P`
    (a fit from the first fraction P of the capture path, pairs rendered along the rest), each
    optionally `@STEPS`; or a path to a JSON file holding a `PerturbConfig.to_dict()` (or
    {"kind": "blur2d", "sigma": s | "quantiles": {...}}, or {"kind": "sparse", "every": K | "n": N, "steps": S,
    "fit": {FitConfig overrides}}, or {"kind": "underfit" | "cross", "fraction": F, "steps": S,
    "fit": {...}}, or {"kind": "strength", "family", "strength": S | "quantiles":
    {"p": [...], "strength": [...]}, "ops": {...}} as `morphgs calibrate` writes), labelled by the
    file stem.
    """
    s = spec.strip()
    low = s.lower()
    if low.startswith("sparse:"):
        return _sparse(s, "sparse", "every", s[7:])
    if low.startswith("sparse-n:"):
        return _sparse(s, "sparse-n", "n", s[9:])
    for kind in ("underfit", "cross"):
        if low.startswith(f"{kind}:"):
            return _fraction_config(s, kind, s[len(kind) + 1:])
    if s.lower().endswith(".json"):
        p = Path(s)
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"--config {spec}: cannot read JSON ({e})") from None
        if not isinstance(d, dict):
            raise ValueError(f"--config {spec}: expected a JSON object")
        if d.get("kind") == "blur2d":
            if "quantiles" in d:  # a sigma distribution, as `morphgs calibrate --family blur2d` writes
                from morphgs.strength import check_quantiles

                _, sig = check_quantiles(d["quantiles"], f"--config {spec}: quantiles")
                if sig[-1] > 256:
                    raise ValueError(f"--config {spec}: quantiles.strength: blur sigmas must be in [0, 256] pixels")
                return ConfigSpec(p.stem, "blur2d", {"quantiles": d["quantiles"]})
            return ConfigSpec(p.stem, "blur2d", {"sigma": float(d.get("sigma", blur_sigma))})
        if d.get("kind") == "sparse":
            if ("every" in d) == ("n" in d):
                raise ValueError(f"--config {spec}: a sparse config needs exactly one of 'every' and 'n'")
            params = {k: d[k] for k in ("every", "n", "steps", "fit") if k in d}
            for k in ("every", "n", "steps"):
                if k in params and (isinstance(params[k], bool) or not isinstance(params[k], int) or params[k] < 1):
                    raise ValueError(f"--config {spec}: '{k}' must be an integer >= 1")
            if "fit" in params and not isinstance(params["fit"], dict):
                raise ValueError(f"--config {spec}: 'fit' must be an object of fit settings")
            return ConfigSpec(p.stem, "sparse", params)
        if d.get("kind") in ("underfit", "cross"):
            unknown = sorted(set(d) - {"kind", "name", "fraction", "steps", "fit"})
            if unknown:
                raise ValueError(f"--config {spec}: unknown field(s) {', '.join(map(repr, unknown))} of a {d['kind']} "
                                 "config (expected fraction, steps, fit)")
            if "fraction" not in d:
                raise ValueError(f"--config {spec}: a {d['kind']} config needs 'fraction'")
            return ConfigSpec(p.stem, str(d["kind"]), _fraction_params(str(d["kind"]), d["fraction"],
                                                                      d.get("steps"), d.get("fit"), f"--config {spec}"))
        if d.get("kind") == "strength":
            return ConfigSpec(p.stem, "strength", _strength_params(d, spec))
        import morphgs

        d = {k: v for k, v in d.items() if k not in ("kind", "name")}
        return ConfigSpec(p.stem, "perturb", dict(morphgs.PerturbConfig.from_dict(d).to_dict()))
    if "~" in s:
        fam, _, strength = s.partition("~")
        try:
            value = float(strength)
        except ValueError:
            raise ValueError(f"--config {spec!r}: the strength after '~' must be a number") from None
        params = _strength_params({"family": fam.lower(), "strength": value}, spec)
        return ConfigSpec(f"{fam.lower()}-s{strength}", "strength", params)
    name, _, factor = s.partition("@")
    name = name.lower()
    if name == "blur2d":
        sigma = float(factor) if factor else float(blur_sigma)
        if not math.isfinite(sigma) or not 0 <= sigma <= 256:
            raise ValueError(f"--config {spec}: blur sigma must be in [0, 256] pixels")
        return ConfigSpec("blur2d" if not factor else f"blur2d-s{factor}", "blur2d", {"sigma": sigma})
    if name not in PRESETS:
        raise ValueError(f"--config {spec!r}: expected one of {', '.join(PRESETS)}, blur2d, NAME@SCALE, "
                         "NAME~STRENGTH, sparse:K, sparse-n:N, underfit:F, cross:P or a .json file")
    import morphgs

    cfg = morphgs.PerturbConfig.preset(name)
    label = name
    if factor:
        try:
            f = float(factor)
        except ValueError:
            raise ValueError(f"--config {spec!r}: the scale after '@' must be a number") from None
        cfg = cfg.scaled(f)
        label = f"{name}-x{factor}"
    return ConfigSpec(label, "perturb", dict(cfg.to_dict()))


def _strength_params(d: dict[str, Any], spec: str) -> dict[str, Any]:
    """Validated params of a "strength" config (a fixed strength or a quantile table)."""
    from morphgs.strength import Strength, check_quantiles

    body = {k: v for k, v in d.items() if k not in ("kind", "name", "quantiles")}
    try:
        cfg = Strength.from_dict(body)
        params: dict[str, Any] = {"family": cfg.family, "ops": cfg.base}
        if cfg.needs_cameras:
            params["train_every"] = cfg.train_every
        if "quantiles" in d:
            if "strength" in d:
                raise ValueError("give either 'strength' or 'quantiles', not both")
            p, s = check_quantiles(d["quantiles"])
            params["quantiles"] = {"p": p, "strength": s}
        else:
            params["strength"] = cfg.strength
    except (TypeError, ValueError) as e:
        raise ValueError(f"--config {spec}: {e}") from None
    return params


@dataclass(frozen=True)
class TrajectoryOptions:
    """How pair cameras are made. `kind`: "auto" (recorded cameras when the scene has them, else
    an orbit), "cameras", "orbit" or "photos" (runs of the capture's own photos, which are then
    the clean side: `curation.photos`). `up`: the world up of orbits around scene files, a rule of
    `trajectory.scene_up` ("file": -y, the loaders' RDF convention; "scene": from the Gaussians;
    "+x" ... "-z" or "X,Y,Z"); the built-in synthetic scenes always orbit around +z."""

    kind: str = "auto"
    stride: int | None = None
    orbit_arc_degrees: float = 60.0
    fov_y_degrees: float = 50.0
    up: str = "file"


def check_up(rule: str) -> str:
    """`rule` when it is a valid up rule of `trajectory.scene_up` (ValueError naming --up otherwise)."""
    from morphgs import trajectory

    if rule in ("file", "scene", "builtin"):
        return rule
    try:
        trajectory.parse_up(rule)
    except ValueError as e:
        raise ValueError(f"--up: {e}, file or scene") from None
    return rule


def uses_orbit(has_cameras: bool, opts: TrajectoryOptions) -> bool:
    """Whether a pair's path is an orbit (not the recorded cameras)."""
    return opts.kind == "orbit" or not has_cameras


def job_up(job: PairJob, scene: Any, recorded: Cameras | None, opts: TrajectoryOptions) -> list[float] | None:
    """The world up of the pair's orbit (None when it follows recorded cameras): +z for the
    built-in synthetic scenes, the recorded cameras' mean up for an orbit of a scene with
    cameras, else `trajectory.scene_up(scene, opts.up)`. A cross pair follows its capture
    whatever `opts.kind`: an orbit's up without recorded cameras, None with them."""
    if job.config.kind == "cross":
        return None if recorded is not None else orbit_up(job, scene, opts)
    return orbit_up(job, scene, opts, recorded) if uses_orbit(recorded is not None, opts) else None


def up_rule(job: PairJob, has_cameras: bool, opts: TrajectoryOptions) -> str:
    """The rule that gives an orbit pair's up (recorded in the manifest as "up_rule")."""
    if job.source.builtin is not None:
        return "builtin"
    return "cameras" if has_cameras else opts.up


def orbit_up(job: PairJob, scene: Any, opts: TrajectoryOptions, recorded: Cameras | None = None) -> list[float]:
    """The world up of an orbit pair: +z for the built-in synthetic scenes, the mean up of the
    recorded cameras when the scene has them (`trajectory.camera_focus`), else
    `trajectory.scene_up(scene, opts.up)`."""
    from morphgs import trajectory
    from morphgs.trajectory.generators import BUILTIN_UP

    if job.source.builtin is not None:
        return [float(v) for v in BUILTIN_UP]
    if recorded is not None:
        return [float(v) for v in trajectory.camera_focus(recorded)[1]]
    return [float(v) for v in trajectory.scene_up(scene, opts.up)[0]]


@dataclass(frozen=True)
class PairJob:
    """One pair to make: a scene, a config and a pair index, with everything derived from them."""

    source: SceneSource
    config: ConfigSpec
    index: int
    pairs_per_scene: int
    seed: int
    split: str
    frames: int
    width: int
    height: int
    run_seed: int = 0

    @property
    def pair_id(self) -> str:
        return f"{self.source.id}/{self.config.label}/{self.index:04d}"

    @property
    def rel_dir(self) -> str:
        return f"pairs/{self.pair_id}"


def make_plan(
    sources: Sequence[SceneSource],
    configs: Sequence[ConfigSpec],
    *,
    pairs_per_scene: int,
    run_seed: int,
    frames: int,
    resolution: tuple[int, int],
    test_fraction: float,
    split_seed: int = 0,
    shard_index: int = 0,
    num_shards: int = 1,
) -> list[PairJob]:
    """All jobs of this shard, ordered scene by scene (so a worker loads each scene once).

    Sharding: jobs are numbered in (scene, pair index, config) order over all scenes, and job j
    belongs to shard j mod num_shards: shards get equal shares whatever the scene sizes, and every
    shard must be given the same scenes and settings.
    """
    if pairs_per_scene < 1:
        raise ValueError(f"pairs_per_scene must be >= 1, got {pairs_per_scene}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if num_shards < 1 or not 0 <= shard_index < num_shards:
        raise ValueError(f"need 0 <= shard_index < num_shards, got {shard_index} of {num_shards}")
    labels = [c.label for c in configs]
    if len(set(labels)) != len(labels):
        raise ValueError(f"configs must have distinct labels, got {labels}")
    jobs = []
    j = 0
    for src in sources:
        split = scene_split(src.id, test_fraction=test_fraction, split_seed=split_seed)
        for k in range(pairs_per_scene):
            seed = pair_seed(run_seed, src.id, k)
            for cfg in configs:
                if j % num_shards == shard_index:
                    jobs.append(PairJob(src, cfg, k, pairs_per_scene, seed, split, frames, *resolution,
                                        run_seed=int(run_seed)))
                j += 1
    return jobs


def job_cameras(job: PairJob, scene: Any, recorded: Cameras | None, opts: TrajectoryOptions) -> Cameras:
    """The camera path of a pair.

    - Recorded cameras (kind "auto"/"cameras" and the scene has them): a smooth constant-speed
      path through the recorded cameras in capture order with as many frames as recorded (at
      least `frames`), cut into clips of `frames` every `stride` frames (default: `frames`);
      pair k takes clip k mod (number of clips).
    - An orbit (kind "orbit") of a scene with recorded cameras circles the point the cameras
      look at, around their mean up, at their median distance, elevation and field of view
      (`trajectory.around_cameras`): pair k starts at 360 k / K degrees from the first recorded
      camera's side and sweeps `orbit_arc_degrees`. A real capture's Gaussians spread far
      beyond its subject, so their box would frame mostly background. Forward-facing cameras
      (nearly parallel axes, no common focus) fall back to the box below, around their mean up.
    - Otherwise an orbit framing the scene's robust bounds (`trajectory.for_scene`) around the
      up of `opts.up` (`job_up`): pair k starts at 360 k / K degrees and sweeps
      `orbit_arc_degrees`; its elevation, in [10, 40] degrees, comes from the pair seed.
    - The built-in synthetic scenes use their own orbit (`synthetic.suggested_orbit`, inside the
      room): pair k's arc starts at 90 + (180 - arc) k / (K - 1) degrees, facing the walls.
    - A `cross` config's pairs, whatever `opts.kind`: a smooth path through the capture views the
      fit did not train on (`morphgs.curation.sparse.cross_path`).
    """
    from morphgs import trajectory

    if opts.kind not in ("auto", "cameras", "orbit", "photos"):
        raise ValueError(f"trajectory must be auto, cameras, orbit or photos, got {opts.kind!r}")
    if opts.kind == "photos" and job.config.kind != "cross":  # the capture's own photos (curation.photos)
        from morphgs.curation.photos import photo_run

        return photo_run(job.source, recorded, job.index, job.frames, (job.width, job.height), opts.stride)[0]
    if job.config.kind == "cross":  # the part of the capture path the fit did not train on
        from morphgs.curation.sparse import cross_path

        return cross_path(job, scene, recorded, opts)
    if opts.kind == "cameras" and recorded is None:
        raise ValueError(f"scene {job.source.id} has no cameras (trajectory 'cameras' was asked)")
    if recorded is not None and opts.kind != "orbit":
        path = trajectory.smooth_path(recorded, max(len(recorded), job.frames))
        cl = trajectory.clips(path, job.frames, stride=opts.stride)
        return cl[job.index % len(cl)]
    if job.source.builtin is not None:
        # The synthetic room: its own orbit (inside the room), on the side facing the walls.
        from morphgs import synthetic

        o = synthetic.suggested_orbit()
        frac = job.index / max(job.pairs_per_scene - 1, 1)
        start = 90.0 + (180.0 - opts.orbit_arc_degrees) * frac
        return trajectory.orbit(o.center, o.radius, o.height - o.center[2], job.frames, start_degrees=start,
                                arc_degrees=opts.orbit_arc_degrees, fov_y_degrees=opts.fov_y_degrees,
                                resolution=(job.width, job.height))
    start = 360.0 * job.index / job.pairs_per_scene
    if recorded is not None and trajectory.camera_focus(recorded)[2]:
        return trajectory.around_cameras(recorded, job.frames, resolution=(job.width, job.height),
                                         start_degrees=start, arc_degrees=opts.orbit_arc_degrees)
    elevation = 10.0 + 30.0 * ((job.seed % 1_000_003) / 1_000_003)
    return trajectory.for_scene(
        scene, job.frames, resolution=(job.width, job.height), fov_y_degrees=opts.fov_y_degrees,
        up=orbit_up(job, scene, opts, recorded), elevation_degrees=elevation,
        start_degrees=360.0 * job.index / job.pairs_per_scene, arc_degrees=opts.orbit_arc_degrees)

