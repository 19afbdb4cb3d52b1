"""`morphgs curate --config underfit:F / cross:P`: Difix3D+'s cheap real-fit pair sources beside
sparse:K. underfit stops the full fit at a fraction of its schedule (fractions of a scene share
one run); cross fits one part of the capture path and renders the pairs along the rest. Every
pair records what its corrupted side cost (`morphgs.curation.costs`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

import morphgs
from fit_helpers import make_dataset
from morphgs.cli import main
from morphgs.curation import costs, curate, load_manifest, parse_config

SMALL: dict[str, Any] = dict(frames=4, resolution=(64, 48), builtin_scenes=1, builtin_gaussians=3000, progress=False,
                             log=lambda m: None)


def _frames(out: Path, rec: dict[str, Any], side: str) -> np.ndarray:
    folder = out / rec["paths"][side]
    return np.stack([np.asarray(Image.open(p)) for p in sorted(folder.glob("*.png"))]).astype(int)


def test_parse_underfit_and_cross_configs(tmp_path: Path) -> None:
    c = parse_config("underfit:0.3")
    assert (c.label, c.kind, c.params) == ("underfit-0.3", "underfit", {"fraction": 0.3})
    c = parse_config("cross:0.50@500")
    assert (c.label, c.kind, c.params) == ("cross-0.5-500steps", "cross", {"fraction": 0.5, "steps": 500})
    f = tmp_path / "uf.json"
    f.write_text(json.dumps({"kind": "underfit", "fraction": 0.25, "steps": 100, "fit": {"strategy": "default"}}))
    c = parse_config(str(f))
    assert (c.label, c.kind, c.params) == ("uf", "underfit", {"fraction": 0.25, "steps": 100,
                                                              "fit": {"strategy": "default"}})
    f.write_text(json.dumps({"kind": "cross", "fraction": 1.0}))
    with pytest.raises(ValueError, match=r"uf\.json: 'fraction' must be a number strictly between 0 and 1, got 1\.0"):
        parse_config(str(f))
    f.write_text(json.dumps({"kind": "cross", "fraction": 0.5, "every": 3}))
    with pytest.raises(ValueError, match=r"unknown field\(s\) 'every' of a cross config"):
        parse_config(str(f))


@pytest.mark.parametrize(("spec", "message"), [
    ("underfit:1.5", "--config 'underfit:1.5': 'fraction' must be a number strictly between 0 and 1, got 1.5"),
    ("underfit:0", "--config 'underfit:0': 'fraction' must be a number strictly between 0 and 1, got 0"),
    ("cross:x", "--config 'cross:x': 'fraction' must be a number strictly between 0 and 1 (cross:P or cross:P@STEPS), "
                "got 'x'"),
    ("underfit:0.5@0", "--config 'underfit:0.5@0': 'steps' must be an integer >= 1, got 0"),
    ("underfit:0.001@100", "--config 'underfit:0.001@100': 'fraction' 0.001 of 100 steps stops before the first step"),
])
def test_a_bad_fraction_is_one_line_naming_the_config_and_the_field(spec: str, message: str, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError) as e:
        parse_config(spec)
    assert str(e.value) == message
    assert main(["curate", "--out", str(tmp_path), "--config", spec, "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(message), err


def test_underfit_stops_the_full_fit_and_its_fractions_share_one_run(tmp_path: Path) -> None:
    out = tmp_path / "data"
    s = curate([], out, configs=["underfit:0.5@40", "underfit:0.25@40"], pairs_per_scene=2, **SMALL)
    assert s.ok and s.done == 4, s.failed
    recs = sorted(load_manifest(out).values(), key=lambda r: r["pair_id"])
    by_cfg = {r["config_name"]: r for r in recs}
    half, quarter = by_cfg["underfit-0.5-40steps"]["fit"], by_cfg["underfit-0.25-40steps"]["fit"]
    # the state of the 40-step fit at steps 20 and 10, from one run of it
    assert (half["steps"], quarter["steps"]) == (20, 10)
    assert half["schedule_steps"] == quarter["schedule_steps"] == 40
    assert half["dir"] == quarter["dir"] and half["run"] == quarter["run"] == "shared"
    assert len(list((out / "fits" / "sample-0").iterdir())) == 1
    run = out / half["dir"] / "run"
    assert not (run / "fit.json").exists()
    loss = (run / "loss.csv").read_text().splitlines()
    assert loss[-1].split(",")[0] == "20"  # stopped there, never run further
    assert sorted(p.name for p in (out / half["dir"] / "snapshots").iterdir()) == ["step_000010", "step_000020"]
    # all capture views but 8 held out train it
    assert half["capture_views"] == 96 and len(half["train_views"]) == 88
    for rec in recs:
        fit = rec["fit"]
        cams = morphgs.Cameras.from_dict(json.loads((out / rec["paths"]["cameras"]).read_text()))
        want = morphgs.render(morphgs.load(out / fit["ply"]), cams).to_uint8()
        got = _frames(out, rec, "corrupted")
        np.testing.assert_array_equal(got, want)
        assert np.abs(got - _frames(out, rec, "clean")).mean() > 2
        # cost: the whole fit up to its step, and this pair's own corrupted side
        t = rec["timings"]
        assert t["fit"] == fit["seconds"] and fit["seconds"] > 0 and t["corrupted"] > 0
    assert half["seconds"] > quarter["seconds"]  # the run's seconds up to each stop
    per_pair = costs.pair_costs(recs)
    for rec in recs:
        assert per_pair[rec["pair_id"]] == pytest.approx(rec["timings"]["corrupted"] + rec["fit"]["seconds"] / 2)
    summary = costs.summarise(r for r in recs if r["config_name"] == "underfit-0.25-40steps")
    assert summary["pairs"] == 2 and summary["fits"] == 1 and summary["seconds_per_pair"] > 0

    # made alone, step 10 of the same schedule is the same scene, byte for byte
    alone = tmp_path / "alone"
    assert curate([], alone, configs=["underfit:0.25@40"], pairs_per_scene=1, **SMALL).ok
    (rec,) = load_manifest(alone).values()
    assert (alone / rec["fit"]["ply"]).read_bytes() == (out / quarter["ply"]).read_bytes()
    # a fraction the shared run has already passed is fitted alone, in branches/
    s2 = curate([], out, configs=["underfit:0.1@40"], pairs_per_scene=1, **SMALL)
    assert s2.ok and s2.done == 1
    tenth = next(r for r in load_manifest(out).values() if r["config_name"] == "underfit-0.1-40steps")["fit"]
    assert tenth["steps"] == 4 and tenth["run"] == "branch" and tenth["dir"] == half["dir"]
    assert (out / half["dir"] / "branches" / "step_000004" / "run" / "point_cloud" / "iteration_4").is_dir()


def test_cross_pairs_are_rendered_along_the_views_the_fit_did_not_train_on(tmp_path: Path) -> None:
    from morphgs.curation.sources import builtin_sources
    from morphgs.curation.sparse import capture_cameras

    out = tmp_path / "data"
    s = curate([], out, configs=["cross:0.5@30"], pairs_per_scene=2, **SMALL)
    assert s.ok and s.done == 2, s.failed
    recs = sorted(load_manifest(out).values(), key=lambda r: r["pair_id"])
    fit = recs[0]["fit"]
    assert fit["train_views"] == list(range(48)) and fit["path_views"] == list(range(48, 96))
    assert fit["steps"] == 30 and fit["seconds"] > 0
    capture = capture_cameras(builtin_sources(1, n_gaussians=3000)[0], None, None, (64, 48))
    centres = np.stack([c.center for c in capture])
    paths = []
    for rec in recs:
        cams = morphgs.Cameras.from_dict(json.loads((out / rec["paths"]["cameras"]).read_text()))
        for c in cams:  # every pair camera is nearer to a capture view of the rest than to a training view
            d = np.linalg.norm(centres - c.center, axis=1)
            assert d[:48].min() > d[48:].min() + 1e-6
        paths.append(np.stack([c.center for c in cams]))
        assert np.abs(_frames(out, rec, "corrupted") - _frames(out, rec, "clean")).mean() > 2
        assert rec["timings"]["corrupted"] > 0 and rec["timings"]["fit"] == fit["seconds"]
    assert not np.allclose(paths[0], paths[1])  # pair k takes clip k of that part


def test_cross_on_recorded_cameras_trains_on_the_first_photos(tmp_path: Path) -> None:
    root, scene, cams = make_dataset(tmp_path / "room", views=16, size=(64, 48), gaussians=3000)
    morphgs.save_ply(scene, root / "scene.ply")
    out = tmp_path / "data"
    s = curate([root], out, configs=["cross:0.5@20", "morphological"], pairs_per_scene=1, frames=4,
               resolution=(64, 48), progress=False, log=lambda m: None)
    assert s.ok, s.failed
    again = curate([root], out, configs=["cross:0.5@20"], pairs_per_scene=1, frames=4, resolution=(64, 48),
                   trajectory="orbit", progress=False, log=lambda m: None)
    assert again.done == 0 and again.skipped == 1  # the cross pair follows its capture whatever --trajectory
    recs = {r["config_name"]: r for r in load_manifest(out).values()}
    assert recs["cross-0.5-20steps"]["up"] is None
    fit = recs["cross-0.5-20steps"]["fit"]
    assert fit["images"] == "images" and fit["train_views"] == list(range(8))
    assert fit["path_views"] == list(range(8, 16))
    np.testing.assert_array_equal(np.asarray(Image.open(out / fit["dir"] / "data" / "images" / "view_00000.png")),
                                  np.asarray(Image.open(root / "images" / "frame_00000.png")))
    pair = morphgs.Cameras.from_dict(json.loads((out / recs["cross-0.5-20steps"]["paths"]["cameras"]).read_text()))
    np.testing.assert_allclose(pair[0].center, cams[8].center, atol=1e-5)  # the path starts at the rest's first view
    # the perturbation pair of the same index follows the recorded path from its start
    other = morphgs.Cameras.from_dict(json.loads((out / recs["morphological"]["paths"]["cameras"]).read_text()))
    np.testing.assert_allclose(other[0].center, cams[0].center, atol=1e-5)
    # perturbation pairs carry their cost too: no fit, their own corrupted side
    t = recs["morphological"]["timings"]
    assert t["fit"] is None and t["corrupted"] > 0
    assert costs.pair_costs([recs["morphological"]])[recs["morphological"]["pair_id"]] == t["corrupted"]
