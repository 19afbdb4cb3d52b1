"""`morphgs calibrate`: the search's failure modes, recovery of hidden known configs from stand-in
"real" pairs, the command end to end (its config used by `curate`), a sparse-view regime
(cached, deterministic for any worker count) and the bad-input errors."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import morphgs
from morphgs import synthetic
from morphgs.calibration import stats
from morphgs.calibration.outputs import document
from morphgs.calibration.pairs import CalibrationError, by_regime, read_real_pairs
from morphgs.calibration.pipeline import calibrate_pairs, parse_family
from morphgs.calibration.run import calibrate, find_scenes, load_scenes
from morphgs.calibration.search import frame_strengths, log_grid, search
from morphgs.cli import main
from morphgs.curation import load_manifest

GAUSSIANS = 20_000
SMALL = ["--frames", "6", "--size", "96x64", "--sample-gaussians", str(GAUSSIANS), "--no-progress",
         "--test-fraction", "0", "-k", "3"]
GRID = log_grid(2.0**-3, 2.0**4, per_octave=2)


def _stand_in(root: Path, name: str, config: dict) -> Path:
    """Stand-in "real" pairs: the built-in scenes curated with a hidden JSON config."""
    f = root / f"{name}.json"
    f.write_text(json.dumps(config))
    out = root / f"real-{name}"
    assert main(["curate", "--out", str(out), "--config", str(f), *SMALL]) == 0
    return out


@pytest.fixture(scope="module")
def hidden_strength(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _stand_in(tmp_path_factory.mktemp("real"), "hidden",
                     {"kind": "strength", "family": "morphological", "strength": 0.8})


@pytest.fixture(scope="module")
def hidden_paper(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _stand_in(tmp_path_factory.mktemp("real"), "paper", {"prune": 0.3, "scale_noise": 0.004,
                                                                 "rotation_noise": 0.05})


def test_search_reports_non_monotone_and_unreachable() -> None:
    # frame j's PSNR falls with s, then rises again past s = 4 (e.g. a scene pruned to black frames)
    offsets = np.array([0.0, 1.0, 2.0, 3.0])

    def measure(s: float) -> np.ndarray:
        return 30.0 - 6.0 * math.log2(s) + offsets if s <= 4 else 18.0 + 3.0 * math.log2(s / 4) + offsets

    grid = log_grid(0.5, 16.0, per_octave=1)
    res = search(measure, [25.0, 24.0, 27.0, 26.5], grid=grid)
    assert not res.monotone and res.violations[0]["from_strength"] == 4.0
    assert res.reachable and abs(res.median_psnr_reached - res.target_median_psnr) <= 0.05
    # frame 0's curve is 30 - 6 log2 s: T = 25 at s = 2^(5/6)
    assert res.frame_strengths[0] == pytest.approx(2 ** (5 / 6), rel=1e-3)
    far = search(measure, [10.0, 11.0, 12.0, 13.0], grid=grid)
    assert not far.reachable and far.most_severe_psnr == pytest.approx(19.5) and far.most_severe_strength == 4.0
    assert far.unreachable_frames == 1.0 and far.median_strength is None
    assert far.quantiles["strength"] == [4.0] * len(far.quantiles["p"])  # the most severe, reported
    mild = search(measure, [40.0, 41.0, 42.0, 43.0], grid=grid)
    assert mild.reachable and mild.below_grid_frames == 1.0 and mild.median_strength == 0.5  # said, not hidden
    s, unreachable = frame_strengths(np.array([1.0, 2.0]), np.array([[30.0, 20.0]]), np.array([31.0]))
    assert s.tolist() == [1.0] and not unreachable[0]


def test_recovers_a_reachable_hidden_strength(hidden_strength: Path, tmp_path: Path) -> None:
    doc = calibrate(realism_steps=0, out=tmp_path / "calib", real=hidden_strength, builtin_gaussians=GAUSSIANS, grid=GRID,
                    plots=False, log=lambda m: None)
    (r,) = doc["results"]
    s = r["search"]
    assert s["monotone"] and s["reachable"] and s["unreachable_frames"] == 0.0
    # the same cameras and seeds: the hidden strength is recovered (bisection tolerance 0.05 dB)
    assert s["median_strength"] == pytest.approx(0.8, rel=0.02)
    q = dict(zip(s["quantiles"]["p"], s["quantiles"]["strength"]))
    assert q[0.05] == pytest.approx(0.8, rel=0.05) and q[0.95] == pytest.approx(0.8, rel=0.05)
    assert set(r["op_shares"]) == {"keep", "log_scale", "rotation"}
    assert sum(r["op_shares"].values()) == pytest.approx(1.0)
    # ops fixed by the user: the same proportions as a file recover the same strength; a keep-only
    # family keeps only its op (in the config and the shares)
    same, keep = tmp_path / "same.json", tmp_path / "keep-only.json"
    same.write_text(json.dumps({"family": "morphological", "ops": {"keep": 0.5, "log_scale": 0.5, "rotation": 0.5}}))
    keep.write_text(json.dumps({"family": "morphological", "ops": {"keep": 0.5}}))
    doc = calibrate(realism_steps=0, out=tmp_path / "calib2", real=hidden_strength, families=[str(same), str(keep)],
                    builtin_gaussians=GAUSSIANS, grid=GRID, plots=False, log=lambda m: None)
    r_same, r_keep = doc["results"]
    assert r_same["family"] == "same" and r_same["search"]["median_strength"] == pytest.approx(0.8, rel=0.02)
    assert r_keep["op_shares"] == {"keep": 1.0} and r_keep["config"]["ops"] == {"keep": 0.5}
    assert json.loads((tmp_path / "calib2" / "configs" / "keep-only-hidden.json").read_text())["ops"] == {"keep": 0.5}


def test_calibrate_pairs_gives_the_commands_results_and_writes_nothing(hidden_strength: Path, tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    doc = calibrate(realism_steps=0, out=tmp_path / "calib", real=hidden_strength, families=["morphological", "blur2d"],
                    builtin_gaussians=GAUSSIANS, grid=GRID, log=lambda m: None)
    # one contact sheet of the regime's families beside the real frames, in the report
    assert (tmp_path / "calib" / "plots" / "hidden-families.png").is_file()
    assert "![](plots/hidden-families.png)" in (tmp_path / "calib" / "report.md").read_text()
    groups = by_regime(read_real_pairs(hidden_strength))
    scenes = load_scenes(find_scenes([], builtin_gaussians=GAUSSIANS), groups)
    empty = tmp_path / "cwd"
    empty.mkdir()
    monkeypatch.chdir(empty)
    said: list[str] = []
    cal = calibrate_pairs(groups, scenes, [parse_family("morphological"), parse_family("blur2d")], grid=GRID,
                          realism_steps=0,
                          say=said.append)
    assert not list(empty.iterdir()) and len(said) == 2
    assert [(r["family"], r["regime"]) for r in cal.results] == [("morphological", "hidden"), ("blur2d", "hidden")]
    assert len(cal.plots) == 2 and cal.resolution == [96, 64] and cal.frames == [6]
    # the command's calibration.json is the document of these results, byte for byte
    mine = document(cal, scenes=doc["scenes"], real=str(hidden_strength), pairs_per_scene=2, seed=0, fit_steps={})
    assert json.dumps(mine, indent=1) + "\n" == (tmp_path / "calib" / "calibration.json").read_text()


def test_the_ablation_stage_writes_the_commands_bytes_and_no_timings_or_lock(hidden_strength: Path,
                                                                              tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from morphgs.ablation.stages.calibration import CONFIG, make

    scenes = []
    for i in range(2):  # the stand-in pairs' scene ids, as scene files
        scenes.append(str(tmp_path / f"sample-{i}.ply"))
        morphgs.save_ply(synthetic.scene(n_gaussians=GAUSSIANS, seed=i), scenes[-1])
    work = tmp_path / "stage"
    work.mkdir()
    make(work, scene_dirs=scenes, real_dir=str(hidden_strength), family="morphological", grid=GRID, objective="psnr")
    calibrate(scenes, tmp_path / "cmd", real=str(hidden_strength), grid=GRID, log=lambda m: None)

    def files(root: Path) -> set[str]:
        return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and "real" not in p.parts}

    stage, cmd = files(work / "calib"), files(tmp_path / "cmd")
    assert {"calibration.json", "report.md", "configs/morphological-hidden.json"} <= stage
    assert any(f.startswith("plots/") for f in stage)
    apart = ("timings.json", "costs.json", "costs.md")
    assert not [f for f in stage if Path(f).name in apart or Path(f).name.startswith(".morphgs")]
    assert cmd - stage == {"timings.json", "costs.json", "costs.md", ".morphgs.lock"}
    for f in sorted(stage):
        assert (work / "calib" / f).read_bytes() == (tmp_path / "cmd" / f).read_bytes(), f
    assert json.loads((work / CONFIG).read_text()) == json.loads((work / "calib" / "configs" /
                                                                  "morphological-hidden.json").read_text())


def test_matches_a_hidden_paper_config(hidden_paper: Path, tmp_path: Path) -> None:
    """A hidden PerturbConfig (its own prune, absolute scale and rotation sigmas) is not in the
    strength family; the calibrated pairs on the held-out scene match its PSNR within 1 dB and
    its SSIM within 0.03 (medians over pairs), and the report names the statistic furthest off."""
    doc = calibrate(realism_steps=0, out=tmp_path / "calib", real=hidden_paper, builtin_gaussians=GAUSSIANS, grid=GRID,
                    log=lambda m: None)
    (r,) = doc["results"]
    g = r["goodness"]
    assert g["held_out"] and g["scenes"] == ["sample-1"] and r["calibration_scenes"] == ["sample-0"]
    real = [p for p in read_real_pairs(hidden_paper) if p.scene == "sample-1"]
    real_psnr = np.median([stats.frame_psnr(p.corrupted, p.clean).mean() for p in real])
    assert abs(g["distances"]["psnr"]) < 2.0
    report = (tmp_path / "calib" / "report.md").read_text()
    assert ("**matched**" in report) == g["matched"] and g["furthest"] in report
    # curate with the produced config: the pairs' PSNR and SSIM match the real ones
    out = tmp_path / "synthetic"
    assert main(["curate", "--out", str(out), "--config", str(tmp_path / "calib" / r["config_file"]), *SMALL]) == 0
    synth = [p for p in read_real_pairs(out) if p.scene == "sample-1"]
    synth_psnr = np.median([stats.frame_psnr(p.corrupted, p.clean).mean() for p in synth])
    assert abs(synth_psnr - real_psnr) < 1.0
    ssim = [np.median([stats.frame_ssim(p.corrupted, p.clean).mean() for p in ps]) for ps in (real, synth)]
    assert abs(ssim[0] - ssim[1]) < 0.03
    assert (tmp_path / "calib" / "plots" / "morphological-paper-psnr-spectrum.png").is_file()


def test_cli_end_to_end_config_used_by_curate(hidden_strength: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    calib = tmp_path / "calib"
    rc = main(["calibrate", "--real", str(hidden_strength), "--out", str(calib), "--family", "morphological",
               "--family", "radiometric", "--sample-gaussians", str(GAUSSIANS), "--no-plots", "--grid", "0.125,16"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "morphological / hidden: reachable" in out and "radiometric / hidden" in out
    doc = json.loads((calib / "calibration.json").read_text())
    assert [r["family"] for r in doc["results"]] == ["morphological", "radiometric"]
    # the family that made the stand-in pairs is named the closest to them, in the JSON, the report
    # and the last line the user sees
    assert [e["family"] for e in doc["ranking"]["hidden"]] == ["morphological", "radiometric"]
    assert "closest to the real hidden pairs: morphological (AUC" in out and out.rstrip().endswith("then radiometric")
    report = (calib / "report.md").read_text()
    assert "| 1 | morphological |" in report and "| 2 | radiometric |" in report
    # the CNN two-sample test ran for both (held-out scene sample-1): it tells the wrong family's
    # pairs from the real ones better than the right one's, and the ranking uses its AUC
    realism = {r["family"]: r["realism"] for r in doc["results"]}
    assert all(v["classifier"]["held_out"] and v["floor"] is not None for v in realism.values())
    assert realism["morphological"]["classifier"]["auc"] < realism["radiometric"]["classifier"]["auc"]
    assert doc["ranking"]["hidden"][0]["auc_kind"] == "cnn"
    assert "## Realism: can a classifier tell them apart?" in report
    cfg = calib / "configs" / "morphological-hidden.json"
    table = json.loads(cfg.read_text())["quantiles"]
    data = tmp_path / "data"
    assert main(["curate", "--out", str(data), "--config", str(cfg), *SMALL]) == 0
    recs = list(load_manifest(data).values())
    assert len(recs) == 6 and all(r["config_name"] == "morphological-hidden" for r in recs)
    assert all(table["strength"][0] <= r["strength"] <= table["strength"][-1] for r in recs)
    assert {"timings.json", "report.md", "calibration.json", "configs"} <= {p.name for p in calib.iterdir()}


def test_family_all_and_the_ranking_order() -> None:
    from morphgs.calibration.pipeline import expand_families, rank_families

    every = ["spatial", "radiometric", "morphological", "naive", "depth", "view_color", "needles", "holes", "dilate",
             "floaters", "shatter", "popping", "haze", "veil", "sparse-like", "blur2d"]
    assert expand_families(["all"]) == every
    assert expand_families(["mine.json", "all", "spatial"]) == ["mine.json", *every, "spatial"]

    def result(family: str, auc: float, excess: float, matched: bool = False) -> dict:
        return {"family": family, "regime": "sparse:20", "goodness": {
            "classifier": {"auc": auc}, "furthest": "spectrum_3", "furthest_excess": excess, "matched": matched}}

    ranked = rank_families([result("morphological", 1.0, 32.0), result("spatial", 0.88, 1.7),
                            result("naive", float("nan"), 1.0), result("blur2d", 1.0, 20.0),
                            result("radiometric", 0.95, 40.0, matched=True)])
    # matched first; then AUC; a tie in AUC goes to the smaller excess; a NaN AUC last
    assert [e["family"] for e in ranked["sparse:20"]] == ["radiometric", "spatial", "blur2d", "morphological", "naive"]
    # with the CNN test, families it tells apart every time (AUC 1.00) go by its separation d'
    # before the statistics' excess
    def cnn(family: str, auc: float, sep: float, excess: float) -> dict:
        return {**result(family, 0.5, excess), "realism": {"classifier": {"auc": auc, "separation": sep}}}

    ranked = rank_families([cnn("shatter", 1.0, 6.0, 0.1), cnn("haze", 1.0, 2.5, 9.0), cnn("holes", 0.9, 9.0, 5.0)])
    assert [(e["family"], e["separation"]) for e in ranked["sparse:20"]] == [("holes", 9.0), ("haze", 2.5),
                                                                           ("shatter", 6.0)]


def test_a_results_files_are_named_by_the_one_slug_rule() -> None:
    from morphgs.calibration.outputs import result_name

    assert result_name("morphological", "sparse:20") == "morphological-sparse-20"
    assert result_name("naive", "sparse-20-1500steps") == "naive-sparse-20-1500steps"
    assert result_name("blur2d", "blur2d-s1.5") == "blur2d-blur2d-s1.5"  # the plots too (they were blur2d-s1-5)
    assert result_name("spatial", "my pairs: 2") == "spatial-my-pairs-2"


def test_sparse_regime_cached_and_deterministic(tmp_path: Path) -> None:
    """The built-in default: four scenes (two calibrate, two held out), the fit length of
    --sample-fit-steps for a regime without @STEPS; resumable and the same bytes for 1 and 2 workers."""
    args = ["calibrate", "--realism-steps", "0", "--regime", "sparse:24", "--sample-fit-steps", "30", "--sample-gaussians", "3000", "--size",
            "48x32", "--frames", "4", "-k", "1", "--no-plots", "--grid", "0.125,16"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    fits = sorted((tmp_path / "a" / "real" / "fits").rglob("fit.json"))
    assert len(fits) == 4
    assert all(json.loads(f.read_text())["steps"] == 30 for f in fits)
    doc = json.loads((tmp_path / "a" / "calibration.json").read_text())
    (r,) = doc["results"]
    assert doc["fit_steps"] == {"sparse:24": 30}
    assert r["calibration_scenes"] == ["sample-0", "sample-2"]
    assert r["goodness"]["held_out"] and r["goodness"]["scenes"] == ["sample-1", "sample-3"]
    stamp = [f.stat().st_mtime_ns for f in fits]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0  # resumed: the fits are reused
    assert [f.stat().st_mtime_ns for f in fits] == stamp
    assert main([*args, "--out", str(tmp_path / "b"), "--workers", "2"]) == 0
    for name in ("calibration.json", "report.md", "configs/morphological-sparse-24.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    # each real pair carries its fit's training cameras (every 24th of the 96-view capture orbit,
    # at the pair's size): a camera op's virtual training views are then the real ones
    from morphgs.calibration.pairs import Bench
    from morphgs.curation.sparse import capture_cameras
    from morphgs.curation.sources import builtin_sources
    from morphgs.strength import Strength

    pairs = read_real_pairs(tmp_path / "a" / "real")
    src = builtin_sources(4, n_gaussians=3000)[0]
    scene = src.load()
    capture = capture_cameras(src, scene, None, (48, 32))
    first = next(p for p in pairs if p.scene == src.id)
    assert first.train_cameras is not None and len(first.train_cameras) == 4
    assert np.allclose(first.train_cameras.world_to_camera, capture.world_to_camera[::24], atol=1e-5)
    assert (first.train_cameras.width, first.train_cameras.height) == (48, 32)
    bench = Bench({src.id: scene}, [first])
    real_views = bench.corrupted(Strength("needles", 2.0), 0)
    path_views = Bench({src.id: scene}, [dataclasses.replace(first, train_cameras=None)]).corrupted(
        Strength("needles", 2.0), 0)
    assert not np.array_equal(real_views, path_views)


def test_underfit_and_cross_regimes_and_the_cost_per_pair(tmp_path: Path) -> None:
    """underfit:F and cross:P are regimes like sparse:K (the built-in fit length when they give no
    @STEPS; underfit regimes of one schedule made in ascending order share one run), and the cost
    per pair of each regime and family lands in costs.json / costs.md, not in the files that
    must be the same bytes on every run."""
    out = tmp_path / "c"
    args = ["calibrate", "--regime", "underfit:0.5", "--regime", "underfit:0.25", "--regime", "cross:0.5",
            "--sample-scenes", "2", "--sample-fit-steps", "20", "--sample-gaussians", "3000", "--size", "48x32",
            "--frames", "4", "-k", "1", "--no-plots", "--grid", "0.125,16", "--out", str(out)]
    assert main(args) == 0
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["regimes"] == ["underfit:0.5", "underfit:0.25", "cross:0.5"]
    assert doc["fit_steps"] == {"underfit:0.5": 20, "underfit:0.25": 20, "cross:0.5": 20}
    recs = load_manifest(out / "real")
    fits = {(r["config_name"], r["scene"]): r["fit"] for r in recs.values()}
    assert fits[("underfit-0.25-20steps", "sample-0")]["steps"] == 5
    assert fits[("underfit-0.5-20steps", "sample-0")]["steps"] == 10
    assert {f["run"] for k, f in fits.items() if k[0].startswith("underfit")} == {"shared"}
    cost = json.loads((out / "costs.json").read_text())
    assert list(cost["regimes"]) == doc["regimes"]
    for c in cost["regimes"].values():
        assert c["pairs"] == 2 and c["fits"] == 2 and c["fit_seconds"] > 0
        assert c["seconds_per_pair"] > c["corrupted_seconds"] > 0
    assert [(c["family"], c["regime"]) for c in cost["families"]] == [("morphological", r) for r in doc["regimes"]]
    assert all(c["seconds_per_pair"] > 0 and c["pairs"] == 1 for c in cost["families"])
    md = (out / "costs.md").read_text()
    assert "| underfit:0.25 | 2 | 2 |" in md and "| morphological | cross:0.5 | 1 |" in md
    assert "second" not in (out / "calibration.json").read_text() + (out / "report.md").read_text()


def _err(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("morphgs calibrate: error: "), err
    return err[0]


def test_bad_input(hidden_strength: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / "c")
    assert ("--family blurry: unknown family; valid families: spatial, radiometric, morphological, naive, depth, "
            "view_color, needles, holes, dilate, floaters, shatter, popping, haze, veil, sparse-like, blur2d") in _err(
        capsys, ["calibrate", "--real", str(hidden_strength), "--family", "blurry", "--out", out])
    bad_family = tmp_path / "fam.json"
    bad_family.write_text(json.dumps({"family": "morphological", "ops": {"prune": 0.5}}))
    assert f"--family {bad_family}: unknown strength op(s) 'prune'" in _err(
        capsys, ["calibrate", "--real", str(hidden_strength), "--family", str(bad_family), "--out", out])
    assert "--regime sparse:96: leaves 1 training view(s) of 96 for scene sample-0" in _err(
        capsys, ["calibrate", "--regime", "sparse:96", "--out", out])
    assert "--regime cross:0.99: leaves 1 of 96 views of scene sample-0 to render the pairs along" in _err(
        capsys, ["calibrate", "--regime", "cross:0.99", "--out", out])
    assert "--regime underfit:2: --config 'underfit:2': 'fraction' must be a number strictly between 0 and 1" in _err(
        capsys, ["calibrate", "--regime", "underfit:2", "--out", out])
    assert "--regime morphological: expected sparse:K, sparse-n:N, underfit:F or cross:P" in _err(
        capsys, ["calibrate", "--regime", "morphological", "--out", out])
    empty = tmp_path / "empty"
    empty.mkdir()
    assert f"--real {empty}: no pairs" in _err(capsys, ["calibrate", "--real", str(empty), "--out", out])
    assert "give at least one --regime" in _err(capsys, ["calibrate", "--out", out])
    # one pair's corrupted frames at another size
    bad = tmp_path / "bad"
    shutil.copytree(hidden_strength, bad)
    rec = sorted(load_manifest(bad).values(), key=lambda r: r["pair_id"])[0]
    for png in sorted((bad / rec["paths"]["corrupted"]).glob("*.png")):
        Image.open(png).resize((48, 32)).save(png)
    msg = _err(capsys, ["calibrate", "--real", str(bad), "--out", out])
    assert f"{bad / rec['paths']['dir']}: corrupted frames (32, 48) x 6 and clean frames (64, 96) x 6 differ" in msg
    other = tmp_path / "other.ply"
    morphgs.save_ply(synthetic.scene(n_gaussians=500, seed=3), other)
    with pytest.raises(CalibrationError, match=r"scene\(s\) sample-0, sample-1 are not among the scenes \(other\)"):
        calibrate([str(other)], out, real=hidden_strength, log=lambda m: None, realism_steps=0)
