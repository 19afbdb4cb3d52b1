"""`morphgs ablate` without running a study: the study file over its presets, --print-config,
--dry-run (plan, job counts, cost), the bad-input errors (one CLI line naming the file and the
problem), the stage cache's keys, and the table generator's best/second marks."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from morphgs.ablation import StudyError, load_study
from morphgs.ablation import cache
from morphgs.ablation.table import format_table, rank_marks
from morphgs.ablation.stats import mean_ci, paired_permutation_p

ENV = {**os.environ, "MORPHGS_NUM_THREADS": "1"}


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "morphgs", "ablate", *args], env=ENV, capture_output=True,
                          text=True, timeout=300, cwd=cwd)


def _study(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "study.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_print_config_pins_every_setting_and_reads_back_to_the_same_study(tmp_path: Path) -> None:
    f = _study(tmp_path, 'preset = "smoke"\n[conditions]\ntrain = ["naive@0.5", "blur2d@3"]\n')
    r = _cli("--study", str(f), "--print-config")
    assert r.returncode == 0, r.stderr
    assert 'preset = "smoke"' in r.stdout and 'train = ["naive@0.5", "blur2d@3"]' in r.stdout
    for section in ("study", "scenes", "split", "capture", "conditions", "regimes", "clips", "model", "training",
                    "sparse", "refit", "metrics"):
        assert f"[{section}]" in r.stdout
    pinned = tmp_path / "pinned.toml"
    pinned.write_text(r.stdout, encoding="utf-8")
    assert load_study(pinned).settings == load_study(f).settings


@pytest.mark.parametrize("preset", ["smoke", "toy", "paper"])
def test_dry_run_shows_the_plan_job_counts_and_a_cost_estimate(preset: str, tmp_path: Path) -> None:
    r = _cli("--preset", preset, "--out", str(tmp_path / "s"), "--dry-run")
    assert r.returncode == 0, r.stderr
    assert "total estimate:" in r.stdout and "stage        jobs" in r.stdout
    s = load_study(None, preset=preset)
    n_cond, n_seed, n_reg = len(s.conditions), len(s.seeds), len(s.regimes)
    line = next(x for x in r.stdout.splitlines() if x.startswith("training "))
    assert int(line.split()[1]) == n_cond * n_seed
    test = int(s["split"]["test"])
    rows = n_cond * n_seed + 3
    line = next(x for x in r.stdout.splitlines() if x.startswith("refine "))
    assert int(line.split()[1]) == test * n_reg * rows
    assert not (tmp_path / "s").exists()  # a dry run writes nothing
    if preset == "paper":
        assert "200 train, 50 test" in r.stdout and "model: sandbox" in r.stdout
        assert "a real run would stop here: model.sd15" in r.stdout
    if preset == "toy":
        assert "6 train, 3 test" in r.stdout and "S18, S20, S24" in r.stdout
        assert "blur2d, naive, spatial, radiometric, morphological, target-S18, target-S20, target-S24" in r.stdout


def test_the_paper_scale_planned_for_a_ray_cluster(tmp_path: Path) -> None:
    """--dry-run --backend ray --cluster: per stage its jobs, CPU- and GPU-hours, wall time at its
    spread over the nodes and peak memory per job; the training's GPU-hours are its jobs' steps."""
    r = _cli("--preset", "paper", "--out", str(tmp_path / "s"), "--dry-run", "--backend", "ray",
             "--cluster", "8x32x8", "-j", "8")
    assert r.returncode == 0, r.stderr
    out = r.stdout.splitlines()
    assert any(x.startswith("cluster plan: 8 node(s) x 32 CPUs x 8 GPUs; Ray tasks of 4 CPU(s), 64 at a time")
               for x in out)
    rows = {x.split()[0]: x.split() for x in out[out.index(next(x for x in out if x.startswith("cluster plan"))) + 2:]
            if x.split() and x.split()[0] in ("captures", "pairfits", "trainsets", "training", "testsets", "refine",
                                               "metrics2d", "metrics3d", "report")}
    assert set(rows) == {"captures", "pairfits", "trainsets", "training", "testsets", "refine", "metrics2d",
                         "metrics3d", "report"}
    assert rows["captures"][1] == "250" and rows["testsets"][1] == "150" and "32 per node" in " ".join(rows["captures"])
    # the targets' sparse fits: one job per (regime, training scene), spread over the cluster
    assert rows["pairfits"][1] == "600" and "75 per node" in " ".join(rows["pairfits"])
    s = load_study(None, preset="paper")
    assert float(rows["training"][3]) == pytest.approx(24 * s["training"]["steps"] * 1.0 / 3600, abs=0.05)
    assert float(rows["training"][2]) == 0.0 and float(rows["metrics3d"][2]) > 0
    assert "GB/GPU" in " ".join(rows["training"])
    total = next(x for x in out if x.startswith("total: "))
    cpu = sum(float(v[2]) for v in rows.values())
    assert total.startswith(f"total: {cpu:.1f} CPU-h") or abs(float(total.split()[1]) - cpu) < 0.2
    for bad, msg in ((["--cluster", "8y32"], "expected NODESxCPUS"),
                     (["--cluster", "2x4"], "use it with --dry-run --backend ray")):
        args = ["--preset", "smoke", "--out", str(tmp_path / "s"), "--dry-run", *bad]
        if "8y32" in bad:
            args += ["--backend", "ray"]
        r = _cli(*args)
        assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(("text", "match"), [
    ('[training]\ncrop = [46, 48]\n',  # the smoke preset's tiny refiner works in blocks of 4
     r"training\.crop must be multiples of 4 for the tiny refiner, got \[46, 48\] \(e\.g\. \[44, 48\]\)"),
    ('[conditions]\ntrain = ["morphologic"]\n', r"conditions\.train: unknown condition 'morphologic'"),
    ('[conditions]\ntrain = ["underfit:1.5"]\n', r"conditions\.train: unknown condition 'underfit:1\.5' \(--config "
     r"'underfit:1\.5': 'fraction' must be a number strictly between 0 and 1, got 1\.5\)"),
    ('[split]\ntrain_ids = ["sample-0"]\n', r"split\.test_ids: empty split"),
    ('[split]\ntest = 3\n', r"empty training split"),
    ('[regimes]\nevery = [30]\n', r"scene sample-\d has 24 capture views, too few for regime S30"),
    ('[model]\nname = "sandbox"\n[model.overrides.model]\nsd15 = "/nonexistent/sd15"\nmotion_adapter = "/x"\n',
     r"model's folders are missing: model\.sd15: /nonexistent/sd15: no such folder"),
    ('[training]\nstepz = 3\n', r"training\.stepz: unknown key"),
    ('[sparse]\ncap_max = 0\n', r"sparse\.cap_max must be >= 1, got 0"),  # refused before any fit
    ('[refit]\nrandom_points = -5\n', r"refit\.random_points must be >= 1, got -5"),
])
def test_bad_study_files_get_one_line_naming_the_file_and_the_problem(tmp_path: Path, text: str, match: str) -> None:
    f = _study(tmp_path, 'preset = "smoke"\n' + text)
    r = _cli("--study", str(f), "--out", str(tmp_path / "s"))
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("morphgs ablate: error: "), r.stderr
    import re

    assert re.search(match, lines[0]), lines[0]
    assert str(f) in lines[0] or "sandbox" in text
    with pytest.raises(StudyError):
        if "sandbox" in text:
            from morphgs.ablation.model_check import check_model_folders

            check_model_folders(load_study(f))
        else:
            from morphgs.ablation.scenes import resolve_scenes

            resolve_scenes(load_study(f))


def test_a_missing_study_file_is_one_line(tmp_path: Path) -> None:
    r = _cli("--study", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "s"))
    assert r.returncode == 1 and r.stderr.strip() == f"morphgs ablate: error: {tmp_path / 'nope.toml'}: no such study file"


def test_stage_keys_hash_every_input_and_a_finished_stage_is_never_remade(tmp_path: Path) -> None:
    a = cache.ref_for(tmp_path, "captures", "s0", {"views": 24, "size": [32, 32]}, version=1)
    assert a == cache.ref_for(tmp_path, "captures", "s0", {"size": [32, 32], "views": 24}, version=1)  # order-free
    assert a.key != cache.ref_for(tmp_path, "captures", "s0", {"views": 25, "size": [32, 32]}, version=1).key
    assert a.key != cache.ref_for(tmp_path, "captures", "s0", {"views": 24, "size": [32, 32]}, version=2).key
    calls = []

    def make(w: Path) -> None:
        calls.append(w)
        (w / "out.txt").write_text("x")

    _, status, _ = cache.run_stage(a, {"views": 24}, make)
    assert status == "computed" and (a.path / "out.txt").read_text() == "x"
    assert json.loads((a.path / "stage.json").read_text())["key"] == a.key
    _, status, _ = cache.run_stage(a, {"views": 24}, make)
    assert status == "reused" and len(calls) == 1

    b = cache.ref_for(tmp_path, "captures", "s1", {"views": 1}, version=1)

    def crash(w: Path) -> None:
        (w / "half.txt").write_text("half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        cache.run_stage(b, {}, crash)
    assert not b.path.exists()  # a crashed stage is never visible as done
    _, status, _ = cache.run_stage(b, {}, make)
    assert status == "computed" and not (b.path / "half.txt").exists()  # non-resumable: a fresh work folder


def test_rank_marks_best_and_second_by_direction_with_ties_and_missing_values() -> None:
    assert rank_marks({"a": 17.0, "b": 18.5, "c": 16.0, "d": 18.0}, True) == {"b": "best", "d": "second"}
    assert rank_marks({"a": 0.4, "b": 0.3, "c": 0.5}, False) == {"b": "best", "a": "second"}
    assert rank_marks({"a": 1.0, "b": 1.0, "c": 0.5, "d": math.nan}, True) == {"a": "best", "b": "best",
                                                                                  "c": "second"}


def _rec(cond: str, seed: object, scene: str, **vals: float) -> dict[str, object]:
    return {"regime": "S20", "condition": cond, "seed": seed, "scene": scene, "clip": "00", **vals}


def test_table_marks_best_bold_and_second_italic_on_a_hand_made_result_set() -> None:
    means = {"naive": (15.0, 0.55), "morphological": (17.5, 0.40), "radiometric": (17.9, 0.37),
             "target-S20": (17.0, 0.41)}
    recs = []
    for cond, (p, lp) in means.items():
        for seed in (0, 1):
            for k, scene in enumerate(("a", "b")):
                off = 0.1 * (seed + k) - 0.1
                recs.append(_rec(cond, seed, scene, psnr2d=p + off, lpips2d=lp + off / 10))
    for ctl, p in (("input", 14.0), ("oracle", math.inf)):
        recs += [_rec(ctl, None, s, psnr2d=p, lpips2d=0.7) for s in ("a", "b")]
    text = format_table(recs, regimes=["S20"], conditions=list(means), severity={"naive": 30.1, "target-S20": 16.2})
    rows = {line.split("|")[2].strip(): line for line in text.splitlines() if line.startswith("| S20 |")}
    cells = {k: [c.strip() for c in v.split("|")[1:-1]] for k, v in rows.items()}
    # columns: regime, set, severity, PSNR2D, SSIM2D, LPIPS2D, ...
    assert cells["radiometric"][3].startswith("**17.900 ± ") and cells["radiometric"][3].endswith("**")
    assert cells["morphological"][3].startswith("*17.500 ± ") and not cells["morphological"][3].startswith("**")
    assert "*" not in cells["naive"][3] + cells["target-S20"][3]
    assert cells["radiometric"][5].startswith("**0.370") and cells["morphological"][5].startswith("*0.400")
    assert cells["(oracle)"][3] == "inf" and "*" not in cells["(input)"][3]  # controls do not compete
    assert cells["naive"][2] == "30.10" and cells["target-S20"][2] == "16.20" and cells["morphological"][2] == "-"
    assert cells["naive"][4] == "n/a"  # no SSIM values given
    assert "### S20: each condition − naive" in text and "### S20: each condition − target-S20" in text
    # the regime's heading says where its inputs sit beside the paper's 12.9-17.1 dB
    assert "S20: inputs (the sparse-view renders) at PSNR2D 14.00 dB; the paper's sit at 12.9-17.1 dB." in text


def test_mean_ci_and_paired_permutation_test() -> None:
    m, ci, n = mean_ci([1.0, 2.0, 3.0])
    # t(0.975, 2 dof) = 4.302653 (SciPy's; the 3-decimal table said 4.303), standard deviation 1
    assert (m, n) == (2.0, 3) and ci == pytest.approx(4.302653 * 1.0 / math.sqrt(3))
    assert math.isnan(mean_ci([5.0])[1]) and mean_ci([])[2] == 0
    # 5 pairs all improved by about 1: the exact two-sided p is 2/32
    assert paired_permutation_p([2.0, 3.1, 4.0, 5.2, 6.0], [1.0, 2.0, 3.0, 4.0, 5.0]) == pytest.approx(2 / 32)
    assert paired_permutation_p([1.0, 2.0], [1.0, 2.0]) == 1.0


def _scene_folder(root: Path, views: int) -> Path:
    """A scene folder as a user has it: the scene file, transforms.json and real images (here the
    renders inverted, so that they cannot be mistaken for renders of the scene)."""
    import numpy as np
    from PIL import Image

    import morphgs
    from fit_helpers import make_dataset

    folder, scene, _ = make_dataset(root, views=views, size=(32, 24), gaussians=1500)
    morphgs.save(scene, folder / "scene.ply")
    for p in sorted((folder / "images").iterdir()):
        Image.fromarray(255 - np.asarray(Image.open(p))).save(p)
    return folder


def test_the_capture_stage_uses_a_scene_folders_cameras_and_real_images(tmp_path: Path) -> None:
    import numpy as np
    from PIL import Image

    from morphgs import media
    from morphgs.ablation.stages import captures
    from morphgs.curation import discover

    folder = _scene_folder(tmp_path / "room", views=10)
    (src,), problems = discover([folder])
    assert not problems
    captures.make(tmp_path / "cap", source=src, views=96, size=(32, 24), up="file", clean_dir=None)
    out, info = captures.load_capture(tmp_path / "cap")
    assert info["views"] == 10 and info["images"] == "images"  # its 10 cameras, not a 96-view orbit
    real = np.stack([np.asarray(Image.open(p)) for p in sorted((folder / "images").iterdir())])
    np.testing.assert_array_equal(media.read_clip(out / "images"), real)
    assert (out / "scene.ply").resolve() == (folder / "scene.ply").resolve()


def test_a_scene_folder_with_too_few_views_for_a_regime_is_named(tmp_path: Path) -> None:
    folder = _scene_folder(tmp_path / "room", views=10)
    from morphgs.ablation.scenes import resolve_scenes

    f = _study(tmp_path, f'preset = "smoke"\n[scenes]\ninputs = ["{folder}"]\n[split]\ntrain_ids = ["room"]\n'
                         'test_ids = ["room"]\n')
    with pytest.raises(StudyError, match=r"scene\(s\) \['room'\] are in both"):
        resolve_scenes(load_study(f))
    f = _study(tmp_path, f'preset = "smoke"\n[scenes]\ninputs = ["{folder}"]\n[regimes]\nevery = [12]\n')
    with pytest.raises(StudyError, match=r"empty training split"):
        resolve_scenes(load_study(f))
    sample = tmp_path / "s2"
    shutil.copytree(folder, sample)
    f = _study(tmp_path, f'preset = "smoke"\n[scenes]\ninputs = ["{folder}", "{sample}"]\n[regimes]\nevery = [12]\n'
                         '[capture]\nsize = [64, 48]\n')
    with pytest.raises(StudyError, match=r"scene (room|s2) has 10 capture views, too few for regime S12 "
                                         r"\(it needs at least 13"):
        resolve_scenes(load_study(f))


def test_a_json_condition_is_read_relative_to_the_study_file_and_named_by_its_stem(tmp_path: Path) -> None:
    import morphgs
    from morphgs.ablation.recipe import build_plan

    (tmp_path / "cfg").mkdir()
    cfg = morphgs.PerturbConfig.preset("morphological").scaled(3.0).to_dict()
    (tmp_path / "cfg" / "strong.json").write_text(json.dumps(cfg), encoding="utf-8")
    f = _study(tmp_path, 'preset = "smoke"\n[conditions]\ntrain = ["cfg/strong.json"]\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = _cli("--study", str(f), "--out", str(tmp_path / "s"), "--dry-run", cwd=elsewhere)
    assert r.returncode == 0, r.stderr
    jobs = build_plan(load_study(f), tmp_path / "s")
    ts = [j for j in jobs if j.ref.stage == "trainsets"]
    assert [j.ref.name for j in ts] == ["strong", "target-S8"]
    spec = ts[0].call_kwargs()["spec"]
    assert spec.params == cfg and spec.label == "strong" and ts[0].inputs["spec"] == spec.as_dict()


def test_a_study_folder_made_with_other_settings_is_refused_naming_the_keys(tmp_path: Path) -> None:
    from morphgs.ablation.executor import check_study_folder

    a = load_study(_study(tmp_path, 'preset = "smoke"\n'))
    check_study_folder(a, tmp_path / "s", recompute=False)
    check_study_folder(a, tmp_path / "s", recompute=False)  # the same settings: fine
    assert load_study(tmp_path / "s" / "study.toml").settings == a.settings  # the pinned settings are kept
    b = load_study(_study(tmp_path, 'preset = "smoke"\n[training]\nsteps = 7\n[clips]\nheldout = [1, 6]\n'))
    with pytest.raises(StudyError, match=r"other settings \(clips\.heldout: \[2, 5\] -> \[1, 6\]; "
                                         r"training\.steps: 20 -> 7\); pass --recompute"):
        check_study_folder(b, tmp_path / "s", recompute=False)
    check_study_folder(b, tmp_path / "s", recompute=True)
    check_study_folder(b, tmp_path / "s", recompute=False)  # now the folder holds b's settings


def test_the_capture_orbit_of_a_scene_file_is_upright_and_up_is_checked(tmp_path: Path) -> None:
    import numpy as np

    import morphgs
    from morphgs import synthetic
    from morphgs.ablation.stages import captures
    from morphgs.camera import Cameras
    from morphgs.curation import discover

    # a z-up scene saved as the loaders give every file: y down ((x, y, z) -> (x, -z, y))
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    base = synthetic.scene(2000, sh_degree=0, seed=3)
    ydown = morphgs.GaussianScene.from_arrays(
        means=np.ascontiguousarray(np.asarray(base.means) @ R.T.astype(np.float32)), quats=base.quats,
        log_scales=base.log_scales, opacity_logits=base.opacity_logits, sh0=base.sh0)
    orbits = {}
    for name, scene, up in (("ydown", ydown, "file"), ("zup", base, "+z")):
        folder = tmp_path / name
        folder.mkdir()
        morphgs.save(scene, folder / "scene.ply")
        (src,), problems = discover([folder])
        assert not problems
        captures.make(tmp_path / f"cap-{name}", source=src, views=8, size=(32, 24), up=up, clean_dir=None)
        out, _ = captures.load_capture(tmp_path / f"cap-{name}")
        orbits[name] = Cameras.from_dict(json.loads((out / "cameras.json").read_text())).camera_to_world
    got, want = orbits["ydown"], orbits["zup"]
    np.testing.assert_allclose(got[:, :3, 3] @ R, want[:, :3, 3], atol=1e-3)  # the same path around the scene
    np.testing.assert_allclose(R.T @ got[:, :3, :3], want[:, :3, :3], atol=1e-4)  # and upright in it
    f = _study(tmp_path, 'preset = "smoke"\n[capture]\nup = "sideways"\n')
    with pytest.raises(StudyError, match=r"capture\.up.*sideways"):
        load_study(f)
    assert load_study(f, up="-y")["capture"]["up"] == "-y"  # --up overrides the file


def test_paired_differences_pair_each_seed_with_the_inputs_scene_and_plot(tmp_path: Path) -> None:
    from morphgs.ablation.plots import deltas, paired_differences

    recs = []
    for scene, base in (("a", 10.0), ("b", 14.0)):
        recs.append({"regime": "S8", "condition": "input", "seed": None, "scene": scene, "clip": "00", "psnr2d": base})
        for seed, gain in ((0, 1.0), (1, 2.0)):
            recs.append({"regime": "S8", "condition": "morphological", "seed": seed, "scene": scene, "clip": "00",
                         "psnr2d": base + gain})
            recs.append({"regime": "S8", "condition": "target-S8", "seed": seed, "scene": scene, "clip": "00",
                         "psnr2d": base + 2 * gain})
    d = paired_differences(recs, "S8", ["morphological", "target-S8", "input"], "psnr2d", "input")
    assert set(d) == {"morphological", "target-S8"}
    m, ci, n = d["morphological"]
    assert (m, n) == (1.5, 4) and ci == pytest.approx(3.182446 * np.std([1, 2, 1, 2], ddof=1) / 2, rel=1e-5)
    m, _, n = paired_differences(recs, "S8", ["morphological"], "psnr2d", "target-S8")["morphological"]
    assert (m, n) == (-1.5, 4)  # against a trained reference: the same (scene, seed) units
    deltas(tmp_path, recs, ["S8"], ["morphological", "target-S8"])
    assert (tmp_path / "deltas.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_real_fit_sources_are_training_conditions_with_their_fit_in_the_estimate(tmp_path: Path) -> None:
    """underfit:F and cross:P are accepted where sparse:K is (`conditions.train`), and the dry
    run's estimate counts their fits (underfit: to its stop step)."""
    from morphgs.ablation.estimate import estimate
    from morphgs.ablation.recipe import build_plan

    def trainsets_estimate(train: str) -> float:
        f = _study(tmp_path, f'preset = "smoke"\n[conditions]\ntargets = false\ntrain = ["{train}"]\n')
        study = load_study(f)
        jobs = build_plan(study, tmp_path / "s")
        (ts,) = [j for j in jobs if j.ref.stage == "trainsets"]
        spec = ts.call_kwargs()["spec"]
        assert spec.kind == train.split(":")[0]
        # the fits are one job per training scene, read by the training set
        fits = [j for j in jobs if j.ref.stage == "pairfits"]
        assert len(fits) == len(ts.kwargs["scene_dirs"]) == 2
        assert {f.ref.key for f in fits} < {u.ref.key for u in ts.depends_on()}
        est = estimate(study, jobs)
        return est["trainsets"] + est["pairfits"]

    base = trainsets_estimate("cross:0.5@1000")  # a fit of 1000 steps per scene
    assert trainsets_estimate("underfit:0.5@2000") == pytest.approx(base)  # stopped at 1000 of 2000
    assert trainsets_estimate("underfit:0.25@2000") < base



@pytest.mark.parametrize("every", [8, 20, 40, 80])
@pytest.mark.parametrize("per_scene", [1, 2])
def test_test_clips_are_novel_views_as_far_from_the_training_cameras_as_a_clip_allows(every: int,
                                                                                      per_scene: int) -> None:
    """A built-in room's 96-view capture orbit: the test clips never pass through a training view
    (whose frame a sparse fit reproduces at ~50 dB, where a refiner can only lose); each is the
    window of its part of the path farthest from the training cameras, and the same every time."""
    from morphgs import trajectory
    from morphgs.ablation.stages.captures import _orbit  # the rooms' own orbit, as a built-in capture has it
    from morphgs.ablation.stages.testsets import clip_cameras, regime_views

    capture = _orbit(type("Builtin", (), {"builtin": 0})(), None, 96, (64, 64), None)
    views = regime_views(len(capture), {"every": every})
    clips, starts = clip_cameras(capture, 16, per_scene, views)
    assert len(clips) == len(starts) == per_scene and all(len(c) == 16 for c in clips)
    assert clip_cameras(capture, 16, per_scene, views)[1] == starts
    train = np.stack([capture[i].center for i in views])
    spacing = np.linalg.norm(capture[1].center - capture[0].center)

    def nearest(clip: object) -> float:
        return float(min(np.linalg.norm(train - c.center, axis=1).min() for c in clip))

    # no clip frame at a training view: at least one capture spacing away where the gap between
    # training views leaves room for 16 frames (every 20, 40, 80), the most a clip can keep otherwise
    room = every - 16
    for clip in clips:
        assert nearest(clip) >= (spacing * 0.99 if room >= 2 else 0.0)
    path = trajectory.smooth_path(capture, 96)
    windows = trajectory.clips(path, 16, stride=1)
    parts = np.array_split(np.arange(len(windows)), per_scene)
    for clip, start, part in zip(clips, starts, parts):
        assert start in part and nearest(clip) == pytest.approx(max(nearest(windows[s]) for s in part))


def test_novel_windows_keep_clear_of_training_cameras_and_hold_the_fewest_when_none_can() -> None:
    """Photos along a line, one unit apart: 8-photo windows as far from the training photos as
    the line allows; where every window holds a training photo (every 8th), one that holds a
    single one, the earliest; with no training photos, each part's first window."""
    from morphgs.ablation.stages.testsets import novel_windows

    line = np.stack([np.arange(40.0), np.zeros(40), np.zeros(40)], axis=1)
    # training photos 0, 20: the window midway in the 19-photo gap (6-13) and in the tail (26-33 and later: 32)
    assert novel_windows(line, line[[0, 20]], 8, 1) == [32]
    assert novel_windows(line, line[[0, 20, 39]], 8, 2) == [6, 26]
    # every 8th is a training photo: each window holds one or two; the first holding one
    assert novel_windows(line, line[::8], 8, 1) == [0]
    held = novel_windows(line, line[::8], 9, 1)  # 9 photos always hold at least one, some two
    assert held == [1]
    assert novel_windows(line, line[:0], 8, 3) == [0, 11, 22]
    assert novel_windows(line[:5], line[:1], 8, 1) == []
