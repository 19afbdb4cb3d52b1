"""Realism (issue 36 §2; docs/calibration.md "Realism"): the CNN two-sample test tells a different
corruption family from the real one and not the same family at other seeds, deterministically;
`morphgs calibrate --objective realism` recovers a hidden mix of the sparse-view ops on a built-in
scene, resumes an interrupted search to the same trials, and its fitted config is what `curate`
and `ablate` take; bad options are one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from morphgs import synthetic, trajectory
from morphgs.calibration.mix import mixed
from morphgs.calibration.objective import given
from morphgs.calibration.realism import Clip, classifier_test, floor_test
from morphgs.cli import main
from morphgs.curation import load_manifest
from morphgs.rendering import render_many
from morphgs.strength import Strength

pytest.importorskip("torch")
pytest.importorskip("optuna")

GAUSSIANS = 20_000
SMALL = ["--frames", "6", "--size", "96x64", "--sample-gaussians", str(GAUSSIANS), "--no-progress",
         "--test-fraction", "0", "-k", "3"]
#: The stand-in "real" pairs' hidden mix of two sparse-view ops, and the family searched.
BASE = Strength("sparse-like", 1.0, {"needles": 0.2, "holes": 0.1})
HIDDEN = {"needles": 0.8, "holes": 0.2}


def _clips(config: Strength, label: int, seed: int) -> list[Clip]:
    """Two built-in scenes, two random 6-frame arcs each, corrupted with `config`."""
    o = synthetic.suggested_orbit()
    rng = np.random.default_rng(7)
    out = []
    for sc in (1, 2):
        scene = synthetic.scene(GAUSSIANS, sh_degree=3, seed=sc)
        for k in range(2):
            cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], 6,
                                    start_degrees=float(rng.uniform(0, 360)), arc_degrees=90, fov_y_degrees=50.0,
                                    resolution=(96, 64))
            clean = np.clip(render_many([scene], cams)[0].rgb, 0, 1)
            bad = np.clip(render_many([config.apply(scene, seed=seed + 10 * sc + k, cameras=cams)], cams)[0].rgb, 0, 1)
            out.append(Clip(bad, clean, f"scene-{sc}", label))
    return out


def test_the_classifier_tells_another_family_apart_but_not_the_same_family_at_other_seeds() -> None:
    real = _clips(Strength("sparse-like", 1.0), 0, seed=0)
    other = _clips(Strength("morphological", 0.5), 1, seed=100)
    same = _clips(Strength("sparse-like", 1.0), 1, seed=500)
    # trained on scene 1, scored on the held-out scene 2
    def split(clips: list[Clip]) -> tuple[list[Clip], list[Clip]]:
        return [c for c in clips if c.scene == "scene-1"], [c for c in clips if c.scene == "scene-2"]

    (rt, rh), (ot, oh), (st, sh) = split(real), split(other), split(same)
    far = classifier_test(rt + ot, rh + oh, steps=120)
    near = classifier_test(rt + st, rh + sh, steps=120)
    assert far["held_out"] and far["frames"] == {"real": 12, "synthetic": 12} and far["bootstrap"] == "pairs"
    assert far["auc"] > 0.9, far
    assert near["auc"] < 0.75, near
    assert near["auc"] < far["auc"]
    # the separation d' ranks them the same way and keeps growing past AUC 1.00
    assert far["separation"] > 1.5 and near["separation"] < far["separation"], (far, near)
    # deterministic: the same clips and seed give the same AUC (torch on one thread while it runs)
    assert classifier_test(rt + st, rh + sh, steps=120)["auc"] == near["auc"]
    # cross-fitted when there is no held-out side; two scenes -> the bootstrap resamples scenes
    crossed = classifier_test(real + other, steps=120)
    assert not crossed["held_out"] and crossed["bootstrap"] == "scenes" and crossed["auc"] > 0.9
    # the floor needs two real pairs per scene and side
    assert np.isnan(floor_test(rt[:1], rh[:1])["auc"])
    with pytest.raises(ValueError, match="need both real"):
        classifier_test(rt, rh)
    # an ensemble of networks per fold (--realism-repeats): the same verdicts, said, deterministic
    far3 = classifier_test(rt + ot, rh + oh, steps=120, repeats=3)
    near3 = classifier_test(rt + st, rh + sh, steps=120, repeats=3)
    assert far3["repeats"] == 3 and "repeats" not in far
    assert far3["auc"] > 0.9 and near3["auc"] < 0.75, (far3, near3)
    assert classifier_test(rt + st, rh + sh, steps=120, repeats=3)["auc"] == near3["auc"]
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        classifier_test(rt + st, rh + sh, steps=120, repeats=0)


def _stand_in(root: Path) -> Path:
    f = root / "hidden.json"
    f.write_text(json.dumps({"kind": "strength", "family": "sparse-like", "strength": 1.0,
                             "ops": mixed(BASE, HIDDEN).base}))
    out = root / "real"
    assert main(["curate", "--out", str(out), "--config", str(f), *SMALL]) == 0
    return out


def _calibrate(real: Path, out: Path, family: Path, trials: int, steps: int, *extra: str) -> dict:
    assert main(["calibrate", "--real", str(real), "--out", str(out), "--family", str(family), "--objective",
                 "realism", "--trials", str(trials), "--realism-steps", str(steps), "--sample-gaussians",
                 str(GAUSSIANS), "--grid", "0.125,16", "--no-plots", *extra]) == 0
    return json.loads((out / "calibration.json").read_text())


@pytest.fixture(scope="module")
def stand_in(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("realism")
    family = root / "needles-holes.json"
    family.write_text(json.dumps({"family": "sparse-like", "ops": BASE.base}))
    return _stand_in(root), family


def test_the_realism_search_recovers_a_hidden_mix_and_curate_and_ablate_take_its_config(
        stand_in: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Stand-in real pairs of needles 0.8 / holes 0.2 on two built-in scenes: eight TPE trials find
    a mix within 0.15 of it, the classifier can tell the most hole-heavy trial's pairs apart better
    than the chosen one's, and the chosen config curates and parses with curate's parser (which
    `ablate` checks its conditions with)."""
    real, family = stand_in
    calib = tmp_path / "calib"
    doc = _calibrate(real, calib, family, 8, 120)
    assert doc["objective"] == "realism"
    (r,) = doc["results"]
    m = r["mix_search"]
    trials = m["trials"]
    assert len(trials) == 8 and m["objective"] == "realism"
    # trial 0 is the family as given (equal weights), so the search never ends worse than it
    assert trials[0]["params"] == given(BASE) and trials[0]["weights"] == {op: 0.5 for op in BASE.base}
    assert min(t["value"] for t in trials) <= trials[0]["value"]
    chosen = trials[m["chosen"]]
    assert chosen["weights"]["needles"] == pytest.approx(HIDDEN["needles"], abs=0.15), trials
    holey = max(trials, key=lambda t: t["weights"]["holes"])
    assert holey["weights"]["holes"] > 0.5 and holey["auc"] > chosen["auc"]
    assert r["config"]["ops"] == pytest.approx(mixed(BASE, chosen["weights"]).base)
    # the held-out test of the chosen config, with its floor
    assert r["realism"]["classifier"]["held_out"] and 0.0 <= r["realism"]["classifier"]["auc"] <= 1.0
    report = (calib / "report.md").read_text()
    assert "## Realism search" in report and "(**chosen**)" in report and "## Realism: can a classifier" in report
    capsys.readouterr()
    # the fitted config: curate draws from it; ablate accepts it as a condition
    cfg = calib / r["config_file"]
    data = tmp_path / "data"
    assert main(["curate", "--out", str(data), "--config", str(cfg), *SMALL]) == 0
    recs = list(load_manifest(data).values())
    assert len(recs) == 6 and all(r_["config"]["ops"] == r["config"]["ops"] for r_ in recs)
    from morphgs.curation.plan import parse_config

    assert parse_config(str(cfg)).kind == "strength"


def test_an_interrupted_search_resumes_to_the_same_trials(stand_in: tuple[Path, Path], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    real, family = stand_in
    whole = _calibrate(real, tmp_path / "whole", family, 3, 30)
    part = tmp_path / "part"
    _calibrate(real, part, family, 2, 30)
    (state,) = (part / "realism").glob("*.jsonl")
    with open(state, "a") as f:  # a line cut short by a kill
        f.write('{"trial": 2, "par')
    capsys.readouterr()
    resumed = _calibrate(real, part, family, 3, 30)
    assert "realism search resumes after 2 finished trial(s)" in capsys.readouterr().err
    a, b = whole["results"][0]["mix_search"]["trials"], resumed["results"][0]["mix_search"]["trials"]
    assert [t["params"] for t in a] == [t["params"] for t in b] and [t["value"] for t in a] == [t["value"] for t in b]
    assert whole["results"][0]["config"] == resumed["results"][0]["config"]
    # other settings: the old state is set aside and the search starts over
    _calibrate(real, part, family, 2, 20)
    assert state.with_suffix(".jsonl.stale").is_file()
    assert len(state.read_text().splitlines()) == 3  # the fingerprint line and two trials
    # an ensemble objective is another setting too; its trials record it
    state.with_suffix(".jsonl.stale").unlink()
    ens = _calibrate(real, part, family, 1, 20, "--realism-repeats", "2")
    assert state.with_suffix(".jsonl.stale").is_file() and len(state.read_text().splitlines()) == 2
    assert ens["results"][0]["mix_search"]["classifier_repeats"] == 2
    assert ens["results"][0]["realism"]["classifier"]["repeats"] == 2


def test_bad_options_are_one_line(stand_in: tuple[Path, Path], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    real, family = stand_in
    out = str(tmp_path / "c")
    for args, msg in ((["--trials", "0"], "--trials must be >= 1"),
                      (["--realism-steps", "0", "--objective", "realism"], "--objective realism needs the classifier"),
                      (["--realism-steps", "-1"], "--realism-steps must be >= 0"),
                      (["--realism-repeats", "0"], "--realism-repeats must be >= 1"),
                      (["--objective", "realism", "--family", "holes"], "--objective realism: no --family has two")):
        fam = [] if "--family" in args else ["--family", str(family)]
        assert main(["calibrate", "--real", str(real), "--out", out, *fam, *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err
    with pytest.raises(SystemExit):
        main(["calibrate", "--real", str(real), "--out", out, "--objective", "beauty"])
    assert "invalid choice: 'beauty'" in capsys.readouterr().err


def test_a_search_with_one_real_calibration_pair_says_what_to_give() -> None:
    """The search cross-fits its classifier on the calibration pairs (each half needs a real one):
    with one real pair it is a CalibrationError saying to give more pairs or scenes, not the
    classifier's own ValueError from deep inside (what `morphgs ablate` on the smoke preset with a
    `realistic:` condition printed before)."""
    from morphgs.calibration.objective import realism_search
    from morphgs.calibration.pairs import CalibrationError

    (real,) = _clips(BASE, 0, seed=0)[:1]
    with pytest.raises(CalibrationError, match=r"needs at least 2 of them, got 1 \(give more pairs per scene"):
        realism_search("mix", BASE, None, [real], np.zeros(6), np.zeros(6, int), real_ids=["a"], grid=[1.0, 2.0])


def test_the_search_objective_ranks_by_auc_then_by_separation() -> None:
    """Two candidates the classifier tells apart every time (AUC 1.00) differ in how far apart it
    puts them (d'); the search's objective prefers the nearer one, never above a candidate with a
    lower AUC, and an unreachable candidate scores above every reachable one."""
    from morphgs.calibration.goodness import auc, separation
    from morphgs.calibration.objective import SEPARATION_CAP, TIE_WEIGHT, UNREACHABLE, objective_value

    rng = np.random.default_rng(0)
    labels = np.repeat([0, 1], 50)
    real = rng.normal(0.0, 1.0, 50)
    near, far = np.concatenate([real, 8.0 + real[::-1]]), np.concatenate([real, 40.0 + real[::-1]])
    assert auc(near, labels) == auc(far, labels) == 1.0
    assert 7.0 < separation(near, labels) < 9.5 and separation(far, labels) > 35
    t_near = {"auc": 1.0, "separation": separation(near, labels)}
    t_far = {"auc": 1.0, "separation": separation(far, labels)}
    assert objective_value(t_near) < objective_value(t_far) == 1.0 + TIE_WEIGHT * SEPARATION_CAP
    assert objective_value({"auc": 0.99, "separation": 1e9}) < objective_value({"auc": 1.0, "separation": 0.0}) + 0.001
    assert objective_value({"auc": 0.5, "separation": -2.0}) == 0.5  # below zero counts as none
    assert objective_value({"auc": 0.6, "separation": float("nan")}) == 0.6
    assert UNREACHABLE > objective_value(t_far)
    assert np.isnan(separation(np.array([1.0, 2.0, 3.0]), np.array([0, 0, 1])))
