"""`morphgs calibrate --objective realism`: the op mix whose pairs a classifier can least tell from
the real ones (docs/calibration.md, "Realism").

A candidate is a weight per op of the family (each in [0, 1], normalised to sum 1; all zero reads
as the preset's equal weights) and, for families with sparse-view ops that use the pair's
cameras, `train_every` (the spacing of the virtual training views along the path). Each candidate
is matched to the real pairs' PSNR as the strength search matches every family (pair by pair, a
scan at one point per octave then bisection), its synthetic pairs are made at their matched
strengths on the calibration scenes, and its score is the cross-fitted AUC of the CNN two-sample
test (`realism.classifier_test`) between them and the real pairs, plus `TIE_WEIGHT` times its
separation d' (`goodness.separation` of the held-out logits, clipped to [0, `SEPARATION_CAP`]): at
most 0.01, so the AUC decides wherever it differs, and where the classifier tells every candidate
apart (AUC 1.00, the common case far from the real failure) the search still moves towards the
ones it separates less, instead of wandering on a flat objective. A candidate that cannot reach
the real median PSNR scores `UNREACHABLE` (1.02) plus its shortfall in tens of dB, worse than any
that can.

The first candidate is the family as given (every op at its base value, equal weights, and its own
`train_every`, or the nearest choice), so the search never ends with a mix its objective scores
worse than the hand-set one. The search is Optuna's TPE sampler (multivariate), asked for one
candidate at a time. Every
finished trial is appended to a JSON-lines state file; a rerun reads it, replays the finished
trials into a fresh study and goes on, and the sampler of trial n is seeded with (seed, n), so an
interrupted search ends where an uninterrupted one does. A state file written for other inputs
(other real pairs, family, seed or settings: its first line's fingerprint) is set aside as
`*.stale` and the search starts over.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.calibration.mix import mixed
from morphgs.calibration.pairs import CalibrationError
from morphgs.calibration.realism import Clip, classifier_test
from morphgs.calibration.search import search
from morphgs.strength import SPARSE_OPS, Strength

__all__ = ["EVERY_CHOICES", "OBJECTIVES", "SEPARATION_CAP", "TIE_WEIGHT", "TRIALS", "UNREACHABLE", "candidate",
           "given", "objective_value", "realism_search"]

#: The objectives `morphgs calibrate --objective` accepts.
OBJECTIVES: tuple[str, ...] = ("psnr", "realism")
#: Trials of the realism search by default.
TRIALS = 16
#: Weight of the separation d' in the search's objective (the AUC's tie-break), and its clip.
TIE_WEIGHT = 1e-3
SEPARATION_CAP = 10.0
#: The objective of a candidate that cannot reach the real pairs' PSNR (plus its shortfall / 10 dB):
#: above any reachable one's (at most 1 + TIE_WEIGHT * SEPARATION_CAP).
UNREACHABLE = 1.02
#: The virtual training views' spacings the search may choose (path frames).
EVERY_CHOICES: tuple[int, ...] = (4, 6, 8, 12, 16)


def objective_value(test: dict[str, Any]) -> float:
    """A reachable candidate's objective from its `classifier_test` result: AUC + TIE_WEIGHT x d'
    clipped to [0, SEPARATION_CAP] (a NaN d' counts 0)."""
    sep = float(test.get("separation", float("nan")))
    sep = min(max(sep, 0.0), SEPARATION_CAP) if not math.isnan(sep) else 0.0
    return float(test["auc"]) + TIE_WEIGHT * sep


def _needs_every(base: Strength) -> bool:
    return any(op in SPARSE_OPS and op not in ("holes", "dilate") for op in base.base)


def candidate(base: Strength, params: dict[str, Any]) -> tuple[Strength, dict[str, float]]:
    """The config of a trial's parameters ({"w_<op>": float, "train_every": int}) and its
    normalised weights."""
    raw = {op: max(float(params.get(f"w_{op}", 0.0)), 0.0) for op in base.base}
    total = sum(raw.values())
    weights = {op: (v / total if total > 0 else 1.0 / len(raw)) for op, v in raw.items()}
    cfg = mixed(base, weights)
    if "train_every" in params:
        cfg = Strength(cfg.family, cfg.strength, cfg.ops, int(params["train_every"]))
    return cfg, weights


def given(base: Strength) -> dict[str, Any]:
    """The trial parameters of the family as given: equal weights (every op at its base value) and
    its `train_every` (the nearest of `EVERY_CHOICES`; ties: the smaller)."""
    params: dict[str, Any] = {f"w_{op}": 1.0 for op in base.base}
    if _needs_every(base):
        params["train_every"] = min(EVERY_CHOICES, key=lambda e: (abs(e - base.train_every), e))
    return params


def _distributions(base: Strength) -> dict[str, Any]:
    from optuna.distributions import CategoricalDistribution, FloatDistribution

    d: dict[str, Any] = {f"w_{op}": FloatDistribution(0.0, 1.0) for op in base.base}
    if _needs_every(base):
        d["train_every"] = CategoricalDistribution(list(EVERY_CHOICES))
    return d


def _fingerprint(base: Strength, real_ids: Sequence[str], *, seed: int, steps: int, grid: Sequence[float],
                 repeats: int = 1) -> str:
    """What a search's trials depend on (not how many there are: a longer search goes on from a
    shorter one's). `repeats` enters only when > 1, so single-network searches keep their state."""
    doc = {"ops": base.base, "family": base.family, "train_every": base.train_every, "real": sorted(real_ids),
           "seed": seed, "steps": steps, "grid": [float(g) for g in grid], "version": 3}
    if repeats > 1:
        doc["repeats"] = repeats
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def _read_state(path: Path, fingerprint: str) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    lines = path.read_text(encoding="utf-8").splitlines()
    try:
        head = json.loads(lines[0]) if lines else {}
    except json.JSONDecodeError:
        head = {}
    if head.get("fingerprint") != fingerprint:
        os.replace(path, path.with_suffix(path.suffix + ".stale"))
        return []
    done = []
    for line in lines[1:]:
        try:
            done.append(json.loads(line))
        except json.JSONDecodeError:  # a line cut short by a kill: that trial is run again
            tmp = path.with_suffix(".tmp")
            tmp.write_text("".join(json.dumps(r) + "\n" for r in [head, *done]), encoding="utf-8")
            os.replace(tmp, path)
            break
    return done


def _append(path: Path, record: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record) + "\n")
        f.flush()
        os.fsync(f.fileno())


def realism_search(label: str, base: Strength, bench: Any, real_clips: Sequence[Clip], real_psnr: np.ndarray,
                   pair_of_frame: np.ndarray, *, real_ids: Sequence[str], grid: Sequence[float], trials: int = TRIALS,
                   seed: int = 0, steps: int = 120, repeats: int = 1, state: Path | None = None,
                   say: Callable[[str], None] | None = None) -> tuple[Strength, dict[str, Any]]:
    """The realism search (module doc) on the calibration pairs: (chosen config, report).

    Args:
        base: the family at strength 1. bench: the calibration pairs' `pairs.Bench`.
        real_clips: the calibration pairs as classifier clips (label 0), in bench order.
        real_psnr, pair_of_frame: their per-frame PSNR and each frame's pair index.
        real_ids: the real pairs' ids (the state file's fingerprint). grid: the strength scan's grid
            (one point per octave of it is scanned). trials: candidates in all (finished ones in
            `state` count). steps: the classifier's training steps per fold. repeats: its networks per
            fold, logits averaged (a steadier objective at `repeats` times the classifier's cost).
        state: the JSON-lines state file (None: nothing written, nothing resumed).

    Raises:
        ImportError: Optuna or torch missing.
        CalibrationError: fewer than two real calibration pairs (the classifier is cross-fitted
            on them: each half needs one).
    """
    if len(real_clips) < 2:
        raise CalibrationError(
            f"{label}: the realism search cross-fits its classifier on the calibration scenes' real pairs and "
            f"needs at least 2 of them, got {len(real_clips)} (give more pairs per scene: calibrate -k, a study's conditions.pairs_per_scene; or more scenes)")
    try:
        import optuna
    except ImportError as e:  # pragma: no cover - metrics extra missing
        raise ImportError("--objective realism needs Optuna: pip install 'morphgs[metrics]'") from e
    say = say or (lambda m: None)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    coarse = list(grid)[::2] if len(grid) >= 6 else list(grid)
    dists = _distributions(base)
    fp = _fingerprint(base, real_ids, seed=seed, steps=steps, grid=coarse, repeats=repeats)
    done = _read_state(state, fp) if state is not None else []
    if state is not None:
        state.parent.mkdir(parents=True, exist_ok=True)
        if not done:
            state.write_text(json.dumps({"fingerprint": fp, "family": label}) + "\n", encoding="utf-8")
        else:
            say(f"calibrate: {label}: realism search resumes after {len(done)} finished trial(s) ({state})")
    study = optuna.create_study(direction="minimize")
    if not done:  # trial 0: the family as given
        study.enqueue_trial(given(base))
    for rec in done:
        study.add_trial(optuna.trial.create_trial(params=rec["params"], distributions=dists, value=rec["value"]))
    rows = list(done)
    for n in range(len(done), trials):
        t0 = time.perf_counter()
        study.sampler = optuna.samplers.TPESampler(seed=seed * 1_000_003 + n, multivariate=True,
                                                   n_startup_trials=min(6, max(trials // 3, 1)))
        trial = study.ask(dists)
        params = dict(trial.params)
        cfg, weights = candidate(base, params)
        def measure(s: float, c: Strength = cfg) -> np.ndarray:
            return np.asarray(bench.frame_psnr(c.at(s)))

        res = search(measure, real_psnr, grid=coarse, pairs=pair_of_frame, iters=6, tol_db=0.1)
        if res.reachable:
            synth = [Clip(bench.corrupted(cfg.at(s), k), bench.clean[k], real_clips[k].scene, 1)
                     for k, s in enumerate(res.pair_strengths)]
            test = classifier_test(list(real_clips) + synth, seed=seed, steps=steps, n_boot=0, repeats=repeats)
            value, auc, sep = objective_value(test), float(test["auc"]), float(test["separation"])
        else:
            auc = sep = float("nan")
            value = UNREACHABLE + max(res.most_severe_psnr - res.target_median_psnr, 0.0) / 10.0
        study.tell(trial, value)
        rec = {"trial": n, "params": params, "value": value, "auc": auc, "separation": sep, "weights": weights,
               "train_every": cfg.train_every, "reachable": res.reachable, "median_strength": res.median_strength,
               "median_psnr_reached": res.median_psnr_reached, "seconds": time.perf_counter() - t0}
        rows.append(rec)
        if state is not None:
            _append(state, rec)
        say(f"calibrate: {label}: realism trial {n + 1}/{trials}: "
            + ", ".join(f"{k} {v:.2f}" for k, v in weights.items())
            + (f", train_every {cfg.train_every}" if "train_every" in params else "")
            + (f": AUC {auc:.3f}, d' {sep:.2f}" if math.isfinite(auc) else f": unreachable ({res.most_severe_psnr:.2f} dB)")
            + f" [{rec['seconds']:.1f} s]")
    best = min(range(len(rows)), key=lambda i: (rows[i]["value"], i))
    cfg, _ = candidate(base, rows[best]["params"])
    # calibration.json is the same bytes on every run: the trials' timings stay in the state file
    info = {"objective": "realism", "trials": [{k: v for k, v in r.items() if k != "seconds"} for r in rows], "chosen": best, "grid": coarse, "classifier_steps": steps,
            **({"classifier_repeats": repeats} if repeats > 1 else {}),
            "seed": seed, "sampler": "optuna TPE (multivariate), seeded per trial"}
    return cfg, info
