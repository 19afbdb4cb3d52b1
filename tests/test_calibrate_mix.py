"""`morphgs calibrate` beyond PSNR: the op-mix search (a hidden op mix is recovered, and matched
better than by the preset's mix) and blur2d as a searchable family (its sigma recovered, its
sigma distribution used by curate)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from morphgs.calibration.mix import mix_distances, mixed, simplex_grid
from morphgs.calibration.run import calibrate
from morphgs.calibration.search import log_grid
from morphgs.cli import main
from morphgs.curation import load_manifest
from morphgs.strength import Strength

GAUSSIANS = 20_000
SMALL = ["--frames", "6", "--size", "96x64", "--sample-gaussians", str(GAUSSIANS), "--no-progress",
         "--test-fraction", "0", "-k", "3"]
GRID = log_grid(2.0**-3, 2.0**4, per_octave=2)
#: The hidden mix: no pruning, scale noise twice the rotation's weight (on the 1/3 grid).
HIDDEN = {"keep": 0.0, "log_scale": 2 / 3, "rotation": 1 / 3}


def _stand_in(root: Path, name: str, config: dict | str) -> Path:
    """Stand-in "real" pairs: the built-in scenes curated with a hidden config."""
    if isinstance(config, dict):
        f = root / f"{name}.json"
        f.write_text(json.dumps(config))
        config = str(f)
    out = root / f"real-{name}"
    assert main(["curate", "--out", str(out), "--config", config, *SMALL]) == 0
    return out


def test_simplex_grid_and_mixed_configs() -> None:
    grid = simplex_grid(["keep", "log_scale", "rotation"], 3)
    assert len(grid) == 10 and grid[0] == dict.fromkeys(("keep", "log_scale", "rotation"), 1 / 3)
    assert all(sum(w.values()) == pytest.approx(1.0) for w in grid)
    assert len({tuple(round(v, 9) for v in w.values()) for w in grid}) == 10
    assert len(simplex_grid(["color", "opacity"], 3)) == 5  # the preset (1/2, 1/2) added to the 1/3 grid
    base = Strength("morphological")
    assert mixed(base, grid[0]).base == pytest.approx(base.base)  # the preset's mix is the family
    m = mixed(base, {"keep": 2 / 3, "log_scale": 1 / 3, "rotation": 0.0})
    # keep's exponent doubles (0.5 ** 2), log_scale keeps its base, rotation is off
    assert m.base == pytest.approx({"keep": 0.25, "log_scale": 0.5})
    with pytest.raises(ValueError, match="steps >= 1"):
        simplex_grid(["keep"], 0)


def test_mix_distances_rank_the_closer_candidate_first() -> None:
    real = [{"ssim": 0.8 + 0.01 * k, "coverage": 0.9, "color_shift": 1.0, "temporal_error": 0.02,
             **{f"spectrum_{b}": -10.0 - b for b in range(6)}} for k in range(4)]
    near = [{**r, "coverage": r["coverage"] - 0.01} for r in real]
    far = [{**r, "coverage": 0.5, "ssim": 0.6} for r in real]
    d_near, d_far = mix_distances(real, [near, far])
    assert d_near["score"] < d_far["score"]
    assert d_far["distances"]["coverage"] > d_near["distances"]["coverage"]
    assert set(d_near["distances"]) == {"ssim", "coverage", "color_shift", "temporal_error", "spectrum"}


def test_search_mix_recovers_a_hidden_mix(tmp_path: Path) -> None:
    """Stand-in real pairs made with the hidden mix at strength 0.6: the search picks exactly that
    mix, whose score (mean W1 distance over SSIM, colour shift, coverage, temporal error and the
    spectrum, pooled-IQR units) is at most half the preset mix's, and then recovers the strength
    (2% tolerance) on the calibration scene."""
    hidden_ops = mixed(Strength("morphological"), HIDDEN).base
    real = _stand_in(tmp_path, "mix", {"kind": "strength", "family": "morphological", "strength": 0.6,
                                       "ops": hidden_ops})
    doc = calibrate(realism_steps=0, out=tmp_path / "calib", real=real, builtin_gaussians=GAUSSIANS, grid=GRID, plots=False,
                    search_mix=True, log=lambda m: None)
    (r,) = doc["results"]
    m = r["mix_search"]
    assert len(m["candidates"]) == 10 and m["scenes"] == ["sample-0"]
    chosen, preset = m["candidates"][m["chosen"]], m["candidates"][m["preset"]]
    assert chosen["weights"] == pytest.approx(HIDDEN)
    assert chosen["score"] <= 0.5 * preset["score"]
    assert r["config"]["ops"] == pytest.approx(hidden_ops)
    assert r["search"]["median_strength"] == pytest.approx(0.6, rel=0.02)
    assert set(r["op_shares"]) == {"log_scale", "rotation"}
    report = (tmp_path / "calib" / "report.md").read_text()
    assert "## Op mix search" in report and "(**chosen**)" in report and "(**preset**)" in report
    # without --search-mix the preset's proportions are kept (the default)
    doc = calibrate(realism_steps=0, out=tmp_path / "plain", real=real, builtin_gaussians=GAUSSIANS, grid=GRID, plots=False,
                    log=lambda m: None)
    assert doc["results"][0]["mix_search"] is None
    assert doc["results"][0]["config"]["ops"] == Strength("morphological").base


def test_blur2d_family_recovers_sigma_and_curate_draws_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    real = _stand_in(tmp_path, "blur", "blur2d@1.5")
    calib = tmp_path / "calib"
    assert main(["calibrate", "--realism-steps", "0", "--real", str(real), "--out", str(calib), "--family", "blur2d", "--sample-gaussians",
                 str(GAUSSIANS), "--no-plots", "--grid", "0.125,16"]) == 0
    capsys.readouterr()
    doc = json.loads((calib / "calibration.json").read_text())
    (r,) = doc["results"]
    assert r["search"]["monotone"] and r["search"]["median_strength"] == pytest.approx(1.5, rel=0.02)
    assert r["op_shares"] == {"sigma": 1.0}
    cfg = json.loads((calib / r["config_file"]).read_text())
    assert cfg["kind"] == "blur2d" and set(cfg) == {"kind", "quantiles"}
    # curate with the sigma distribution: each pair draws its sigma, recorded as its strength
    data = tmp_path / "data"
    assert main(["curate", "--out", str(data), "--config", str(calib / r["config_file"]), *SMALL]) == 0
    recs = list(load_manifest(data).values())
    assert len(recs) == 6
    lo, hi = cfg["quantiles"]["strength"][0], cfg["quantiles"]["strength"][-1]
    assert all(lo <= rec["strength"] <= hi for rec in recs)
    assert all(rec["strength"] == pytest.approx(1.5, rel=0.05) for rec in recs)
    bad = tmp_path / "bad-blur.json"
    bad.write_text(json.dumps({"kind": "blur2d", "quantiles": {"p": [0, 1], "strength": [1, 300]}}))
    assert main(["curate", "--out", str(tmp_path / "x"), "--config", str(bad), *SMALL]) == 2
    assert "blur sigmas must be in [0, 256]" in capsys.readouterr().err
