"""A calibrated condition in `morphgs ablate` (`calibrated:FAMILY`, issue 23), end to end through
the CLI on the smoke preset: per regime, the family is calibrated against the regime's target
training set (built even with targets = false), a training set is curated with the calibrated
strength distribution, and its refiners get rows in that regime. Its training pairs are far
closer to the target's severity than the family's default strength; a rerun recomputes nothing;
two workers give the same bytes; --dry-run counts and estimates the stage; an unknown family is
one line naming conditions.train."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("accelerate")
pytest.importorskip("matplotlib")

ENV = {**os.environ, "MORPHGS_NUM_THREADS": "2"}
STUDY = """preset = "smoke"
[conditions]
train = ["morphological", "calibrated:morphological", "calibrated:fams/holes-dilate.json"]
targets = false
"""
CAL = "calibrated:morphological-S8"
#: a family file's ops and proportions (`calibrate --family FILE.json`), given relative to the study
FAMILY = {"family": "morphological", "ops": {"holes": 0.1, "dilate": 0.3}}
FAM_LABEL = "calibrated:holes-dilate-S8"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "morphgs", "ablate", *args], env=ENV, capture_output=True,
                          text=True, timeout=900)


def _ablate(*args: str) -> subprocess.CompletedProcess[str]:
    r = _run(*args)
    assert r.returncode == 0, r.stderr[-4000:]
    return r


def _last_run(study: Path) -> dict:
    return json.loads((study / "runs.jsonl").read_text().splitlines()[-1])


@pytest.fixture(scope="module")
def study_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("calstudy") / "study.toml"
    p.write_text(STUDY, encoding="utf-8")
    (p.parent / "fams").mkdir()
    (p.parent / "fams" / "holes-dilate.json").write_text(json.dumps(FAMILY), encoding="utf-8")
    return p


@pytest.fixture(scope="module")
def cal(study_file: Path) -> Path:
    out = study_file.parent / "study"
    _ablate("--study", str(study_file), "--out", str(out))
    return out


def test_a_calibrated_condition_runs_end_to_end_and_is_closer_to_the_target_severity(cal: Path) -> None:
    counts = _last_run(cal)["counts"]
    # trainsets: morphological, target-S8 (built for the calibration only: targets = false) and the
    # two calibrated sets; trainings: morphological and the calibrated conditions, 2 seeds each
    assert counts["calibration"] == {"computed": 2, "reused": 0}
    assert counts["trainsets"] == {"computed": 4, "reused": 0}
    assert counts["training"] == {"computed": 6, "reused": 0}
    res = json.loads((cal / "results.json").read_text())
    fam = f"calibrated:{cal.parent / 'fams' / 'holes-dilate.json'}-S8"  # the file, resolved from the study's folder
    rows = {(r["condition"], r["seed"]) for r in res["records"] if r["seed"] is not None}
    assert rows == {(c, s) for c in ("morphological", CAL, fam) for s in (0, 1)}
    sev = res["severity"]
    assert set(sev) == {"morphological", "target-S8", CAL, fam}
    # the point of the calibration: its pairs are as corrupted as the real sparse-view pairs, the
    # default-strength family's are not (smoke: about 21 dB against 11 dB)
    assert abs(sev[CAL] - sev["target-S8"]) < 0.5 * abs(sev["morphological"] - sev["target-S8"]), sev
    c = res["calibration"][CAL]
    assert c["family"] == "morphological" and c["reachable"] and c["median_strength"] > 1.0
    # the stage's own outputs: the config the training set was curated with, calibrate's report
    (cdir,) = (cal / "calibration").glob("calibrated_morphological-S8-*")
    config = json.loads((cdir / "config.json").read_text())
    assert config["kind"] == "strength" and config["family"] == "morphological" and "quantiles" in config
    assert (cdir / "calib" / "calibration.json").is_file() and (cdir / "calib" / "report.md").is_file()
    # written by the stage itself: no timings (wall times) and no lock file of the command
    assert not [p for p in (cdir / "calib").rglob("*") if p.name == "timings.json" or p.name.startswith(".morphgs")]
    # every calibrated pair records the strength it drew from that distribution
    (tdir,) = (cal / "trainsets").glob("calibrated_morphological-S8-*")
    recs = [json.loads(line) for m in sorted((tdir / "data").glob("manifest*.jsonl"))
            for line in m.read_text().splitlines() if line.strip()]
    lo, hi = config["quantiles"]["strength"][0], config["quantiles"]["strength"][-1]
    assert recs and all(lo - 1e-9 <= r["strength"] <= hi + 1e-9 for r in recs)
    table = (cal / "table.md").read_text()
    assert f"| S8 | {CAL} |" in table and "| S8 | target-S8 |" not in table
    assert f"- {CAL}: morphological calibrated against target-S8's real pairs" in table
    assert "S8: each calibrated condition − its family at the default strength" in table
    assert f"| {CAL} | " in table.split("its family at the default strength")[1]
    # the family file's condition: calibrated with the file's ops in its proportions, labelled by
    # the file's name in the table and the folders
    (fdir,) = (cal / "calibration").glob("calibrated_holes-dilate-S8-*")
    fconfig = json.loads((fdir / "config.json").read_text())
    assert fconfig["kind"] == "strength" and set(fconfig["ops"]) == {"holes", "dilate"}, fconfig
    assert fconfig["ops"]["dilate"] / fconfig["ops"]["holes"] == pytest.approx(3.0)
    c = res["calibration"][fam]
    assert c["family"] == "holes-dilate" and c["reachable"]
    assert abs(sev[fam] - sev["target-S8"]) < 1.5, sev
    assert f"| S8 | {FAM_LABEL} |" in table and f"- {FAM_LABEL}: holes-dilate calibrated against" in table


def test_a_rerun_recomputes_nothing(cal: Path, study_file: Path) -> None:
    before = (cal / "results.json").read_bytes()
    r = _ablate("--study", str(study_file), "--out", str(cal))
    assert "0 stage output(s) computed" in r.stderr
    assert all(c["computed"] == 0 for c in _last_run(cal)["counts"].values())
    assert (cal / "results.json").read_bytes() == before


def test_two_workers_give_the_same_bytes(cal: Path, study_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "j2"
    _ablate("--study", str(study_file), "--out", str(out), "-j", "2")
    for f in ("results.json", "results.csv", "table.md"):
        assert (out / f).read_bytes() == (cal / f).read_bytes(), f
    mine = sorted((cal / "calibration").glob("*/config.json"))
    theirs = sorted((out / "calibration").glob("*/config.json"))
    assert len(mine) == 2 and [p.parent.name for p in mine] == [p.parent.name for p in theirs]
    assert [p.read_bytes() for p in mine] == [p.read_bytes() for p in theirs]


def test_dry_run_counts_and_estimates_the_calibration_stage(study_file: Path, tmp_path: Path) -> None:
    r = _ablate("--study", str(study_file), "--out", str(tmp_path / "dry"), "--dry-run")
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("calibration"))
    jobs, todo = line.split()[1:3]
    assert (jobs, todo) == ("2", "2") and line.split()[3] != "0", line
    assert f"conditions: morphological, {CAL}, {FAM_LABEL};" in r.stdout
    assert not (tmp_path / "dry").exists()


def test_the_estimate_prices_a_realism_calibration_by_its_search(tmp_path: Path) -> None:
    """A realistic:FAMILY condition searches the op mix first (TRIALS candidates, each a strength
    match and a classifier): its calibration is estimated at that many times a PSNR calibration's
    share, not as one."""
    from morphgs.ablation import load_study
    from morphgs.ablation.estimate import UNIT, estimate
    from morphgs.ablation.recipe import build_plan
    from morphgs.calibration.objective import TRIALS

    def calibration(cond: str) -> float:
        f = tmp_path / "e.toml"
        f.write_text(f'preset = "smoke"\n[conditions]\ntrain = ["{cond}"]\n', encoding="utf-8")
        study = load_study(f)
        return estimate(study, build_plan(study, tmp_path / "s"))["calibration"]

    psnr, realism = calibration("calibrated:radiometric"), calibration("realistic:radiometric")
    assert realism == pytest.approx(psnr * (1 + TRIALS * UNIT["realism_trial"]))


def test_an_unknown_calibrated_family_is_one_line_naming_conditions_train(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text('preset = "smoke"\n[conditions]\ntrain = ["calibrated:morphologic"]\n', encoding="utf-8")
    r = _run("--study", str(f), "--out", str(tmp_path / "s"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"morphgs ablate: error: {f}: conditions.train: unknown condition "
                               "'calibrated:morphologic' (calibrated:FAMILY and realistic:FAMILY take one of the families "), lines[0]


def test_the_calibration_key_is_the_target_sets_key_the_family_and_the_grid(tmp_path: Path) -> None:
    from morphgs.ablation import load_study
    from morphgs.ablation.recipe import build_plan

    def plan(text: str) -> dict[str, object]:
        f = tmp_path / "p.toml"
        f.write_text('preset = "smoke"\n' + text, encoding="utf-8")
        return {f"{j.ref.stage}/{j.ref.name}": j for j in build_plan(load_study(f), tmp_path / "s")}

    base = plan('[conditions]\ntrain = ["calibrated:morphological", "calibrated:naive"]\n')
    morph, naive = base["calibration/calibrated_morphological-S8"], base["calibration/calibrated_naive-S8"]
    target = base["trainsets/target-S8"]
    # both calibrate against the one target set of the regime (also trained: targets = true)
    assert morph.inputs["real_dir"] == naive.inputs["real_dir"] == {"out": target.ref.key, "sub": "data"}
    assert "training/target-S8-s0" in base
    assert morph.ref.key != naive.ref.key and morph.inputs["family"] == "morphological"
    assert base["trainsets/calibrated_morphological-S8"].inputs["calibration_dir"] == {"out": morph.ref.key, "sub": ""}
    # a change of the target's sparse fits changes the calibration and what reads it, not the others
    other = plan('[conditions]\ntrain = ["calibrated:morphological", "calibrated:naive"]\n[sparse]\nsteps = 151\n')
    assert other["calibration/calibrated_morphological-S8"].ref.key != morph.ref.key
    assert other["captures/sample-0"].ref.key == base["captures/sample-0"].ref.key
    # without targets, the target set is still built for the calibration, but not trained
    lean = plan('[conditions]\ntrain = ["calibrated:morphological"]\ntargets = false\n')
    assert "trainsets/target-S8" in lean and not any(k.startswith("training/target") for k in lean)
    assert lean["calibration/calibrated_morphological-S8"].ref.key == morph.ref.key


def test_a_realistic_condition_searches_the_mix_and_hyphenated_families_parse(tmp_path: Path) -> None:
    """`realistic:FAMILY` is a calibrated condition whose calibration runs `--objective realism`
    (its own key), and a family with '-' (sparse-like) keeps its name and regime."""
    from morphgs.ablation import load_study
    from morphgs.ablation.conditions import Condition
    from morphgs.ablation.recipe import build_plan

    c = Condition.parse("realistic:sparse-like-S20")
    assert (c.kind, c.family, c.regime, c.objective) == ("calibrated", "sparse-like", "S20", "realism")
    c = Condition.parse("calibrated:sparse-like")
    assert (c.family, c.regime, c.objective) == ("sparse-like", None, "psnr")
    f = tmp_path / "p.toml"
    f.write_text('preset = "smoke"\n[conditions]\ntrain = ["calibrated:sparse-like", "realistic:sparse-like"]\n',
                 encoding="utf-8")
    study = load_study(f)
    assert [c.name for c in study.conditions][:2] == ["calibrated:sparse-like-S8", "realistic:sparse-like-S8"]
    jobs = {f"{j.ref.stage}/{j.ref.name}": j for j in build_plan(study, tmp_path / "s")}
    psnr, real = jobs["calibration/calibrated_sparse-like-S8"], jobs["calibration/realistic_sparse-like-S8"]
    assert (psnr.inputs["objective"], real.inputs["objective"]) == ("psnr", "realism")
    assert psnr.inputs["family"] == real.inputs["family"] == "sparse-like" and psnr.ref.key != real.ref.key
    f.write_text('preset = "smoke"\n[conditions]\ntrain = ["realistic:sparse-liked"]\n', encoding="utf-8")
    r = _run("--study", str(f), "--out", str(tmp_path / "s"))
    assert r.returncode == 1 and "unknown condition 'realistic:sparse-liked'" in r.stderr


def test_a_family_file_is_keyed_by_its_contents_and_bad_ones_are_one_line(tmp_path: Path) -> None:
    """`calibrated:FILE.json` / `realistic:FILE.json` (a path relative to the study file): the
    calibration is keyed by the file's bytes (an edit recomputes it and what reads it, nothing
    upstream; a byte-identical copy elsewhere keeps its key), labelled by the file's stem; a
    missing, unreadable or wrong file, two files of one name, or `realistic:` of a one-op family
    (there is no mix to search), is one line naming the field."""
    from morphgs.ablation import load_study
    from morphgs.ablation.recipe import build_plan

    (tmp_path / "fams").mkdir()
    fam = tmp_path / "fams" / "mix.json"
    fam.write_text(json.dumps(FAMILY), encoding="utf-8")

    def plan(train: str, where: Path = tmp_path) -> dict[str, object]:
        f = where / "p.toml"
        f.write_text(f'preset = "smoke"\n[conditions]\ntrain = [{train}]\n', encoding="utf-8")
        return {f"{j.ref.stage}/{j.ref.name}": j for j in build_plan(load_study(f), tmp_path / "s")}

    base = plan('"calibrated:fams/mix.json", "realistic:fams/mix.json"')
    psnr, real = base["calibration/calibrated_mix-S8"], base["calibration/realistic_mix-S8"]
    assert psnr.inputs["family"] == real.inputs["family"] == {"file_sha256": hashlib.sha256(fam.read_bytes()).hexdigest()}
    assert (psnr.inputs["objective"], real.inputs["objective"]) == ("psnr", "realism") and psnr.ref.key != real.ref.key
    assert {"training/calibrated_mix-S8-s0", "training/realistic_mix-S8-s1"} <= set(base)
    fam.write_text(json.dumps({**FAMILY, "ops": {"holes": 0.2, "dilate": 0.3}}), encoding="utf-8")
    edited = plan('"calibrated:fams/mix.json", "realistic:fams/mix.json"')
    assert edited["calibration/calibrated_mix-S8"].ref.key != psnr.ref.key
    assert edited["training/calibrated_mix-S8-s0"].ref.key != base["training/calibrated_mix-S8-s0"].ref.key
    assert edited["trainsets/target-S8"].ref.key == base["trainsets/target-S8"].ref.key
    fam.write_text(json.dumps(FAMILY), encoding="utf-8")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "mix.json").write_bytes(fam.read_bytes())
    moved = plan('"calibrated:elsewhere/mix.json"')
    assert moved["calibration/calibrated_mix-S8"].ref.key == psnr.ref.key

    (tmp_path / "fams" / "bad.json").write_text(json.dumps({"family": "morphological", "ops": {"hole": 0.1}}),
                                                 encoding="utf-8")
    (tmp_path / "fams" / "torn.json").write_text('{"family": "morph', encoding="utf-8")
    (tmp_path / "fams" / "one.json").write_text(json.dumps({"family": "shatter", "ops": {"shatter": 1.0}}),
                                                 encoding="utf-8")
    for train, says in (('"realistic:shatter"', "realistic: searches the mix of a family's ops and shatter has 1 "
                                                "(shatter); use calibrated:shatter"),
                        ('"realistic:fams/one.json"', "one.json has 1 (shatter)"),
('"calibrated:fams/none.json"', "'calibrated:fams/none.json': no such family file"),
                        ('"realistic:fams/bad.json"', "bad.json': unknown strength op(s) 'hole'"),
                        ('"calibrated:fams/torn.json"', "torn.json': cannot read JSON"),
                        ('"calibrated:fams/mix.json", "calibrated:elsewhere/mix.json"',
                         "have the same label 'calibrated:mix' (JSON files are labelled by their name): rename one")):
        f = tmp_path / "bad.toml"
        f.write_text(f'preset = "smoke"\n[conditions]\ntrain = [{train}]\n', encoding="utf-8")
        r = _run("--study", str(f), "--out", str(tmp_path / "s"), "--dry-run")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 1 and len(lines) == 1, r.stderr
        assert lines[0].startswith(f"morphgs ablate: error: {f}: conditions.train: ") and says in lines[0], lines[0]
