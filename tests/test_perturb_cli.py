"""`morphgs perturb` end to end on a real scene file (fixtures/ATTRIBUTION.md: splatapult_test.ply,
hyperlogic/splatapult, MIT)."""

from __future__ import annotations

import json

import numpy as np

import morphgs
from morphgs.cli import main


def test_cli_writes_a_perturbed_ply_and_reports(fixtures_dir, tmp_path, capsys) -> None:
    src = fixtures_dir / "splatapult_test.ply"
    out = tmp_path / "out.ply"
    mask_path = tmp_path / "mask.npy"
    rc = main(["perturb", str(src), str(out), "--preset", "morphological", "--seed", "7",
               "--prune", "0.3", "--mask", str(mask_path)])
    assert rc == 0
    text = capsys.readouterr().out
    clean = morphgs.load(src)
    got = morphgs.load(out)
    mask = np.load(mask_path)
    assert f"{len(clean)} in, {len(got)} kept, {len(clean) - len(got)} pruned" in text
    assert '"prune": 0.3' in text and '"position_jitter": null' in text
    # same as the Python API with the same config and seed (up to the PLY's float32 round trip)
    cfg = morphgs.PerturbConfig.preset("morphological")
    cfg = morphgs.PerturbConfig(**{**cfg.to_dict(), "prune": 0.3})
    ref, ref_mask = morphgs.perturb(clean, cfg, seed=7, return_mask=True)
    np.testing.assert_array_equal(mask, ref_mask)
    np.testing.assert_array_equal(got.means, ref.means)
    np.testing.assert_allclose(got.quats, ref.quats, atol=1e-6)
    np.testing.assert_array_equal(got.log_scales, ref.log_scales)
    np.testing.assert_array_equal(got.sh_rest, clean.sh_rest[mask])


def test_cli_json_summary_with_disabled_ops_and_config_file(fixtures_dir, tmp_path, capsys) -> None:
    src = fixtures_dir / "metalsplatter_train3.ply"
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(morphgs.PerturbConfig.preset("naive").to_json())
    rc = main(["perturb", str(src), str(tmp_path / "o.ply"), "--config", str(cfg_file),
               "--no-prune", "--seed", "1", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["kept"] == summary["gaussians_in"] == 3 and summary["pruned"] == 0
    assert summary["config"]["prune"] is None and summary["config"]["color_noise"] == 0.05


def test_cli_rejects_invalid_values_with_a_message(fixtures_dir, tmp_path, capsys) -> None:
    src = fixtures_dir / "metalsplatter_train3.ply"
    rc = main(["perturb", str(src), str(tmp_path / "o.ply"), "--seed", "1", "--prune", "1.5"])
    assert rc == 2
    assert "prune must be a probability" in capsys.readouterr().err
    rc = main(["perturb", str(src), str(tmp_path / "o.ply"), "--seed", "1", "--prune", "0.2",
               "--no-prune"])
    assert rc == 2
    assert not (tmp_path / "o.ply").exists()


def test_cli_strength_forms_match_the_api(fixtures_dir, tmp_path, capsys) -> None:
    """`--preset FAMILY~S` and a strength `--config` file (a strength distribution, as morphgs
    calibrate writes: the strength drawn from --seed as curate draws it) give the API's bytes."""
    from morphgs.strength import Strength, draw_strength

    src = fixtures_dir / "splatapult_test.ply"
    clean = morphgs.load(src)
    out = tmp_path / "s.ply"
    assert main(["perturb", str(src), str(out), "--preset", "morphological~2.5", "--seed", "7"]) == 0
    assert "family morphological, strength 2.5" in capsys.readouterr().out
    ref = Strength("morphological", 2.5).apply(clean, seed=7)
    got = morphgs.load(out)
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh0"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f))
    table = {"kind": "strength", "family": "naive", "ops": {"keep": 0.8, "color": 0.1, "rotation": 0.3},
             "quantiles": {"p": [0.0, 0.5, 1.0], "strength": [0.5, 1.0, 4.0]}}
    cfg = tmp_path / "calibrated.json"
    cfg.write_text(json.dumps(table))
    assert main(["perturb", str(src), str(out), "--config", str(cfg), "--seed", "11", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    drawn = draw_strength(table, 11)
    assert summary["strength"] == drawn and 0.5 < drawn < 4.0
    assert summary["config"]["ops"] == table["ops"]
    ref = Strength("naive", drawn, table["ops"]).apply(clean, seed=11)
    got = morphgs.load(out)
    assert summary["kept"] == len(ref) == len(got)
    np.testing.assert_array_equal(got.quats, ref.quats)
    np.testing.assert_array_equal(got.sh0, ref.sh0)


def test_cli_strength_errors_name_the_option(fixtures_dir, tmp_path, capsys) -> None:
    src = fixtures_dir / "metalsplatter_train3.ply"
    o = str(tmp_path / "o.ply")

    def err(argv: list[str]) -> str:
        assert main(["perturb", str(src), o, "--seed", "1", *argv]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("morphgs perturb: error: "), lines
        return lines[0]

    assert "--preset 'morphological~x': the strength after '~' must be a number" in err(["--preset", "morphological~x"])
    assert "--preset blurry~2" in err(["--preset", "blurry~2"]) and "unknown family" in err(["--preset", "blurry~2"])
    assert "--preset blurry: expected one of spatial" in err(["--preset", "blurry"])
    assert "--prune, --strength set PerturbConfig fields" in err(["--preset", "spatial~1", "--prune", "0.2",
                                                                  "--strength", "2"])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "strength", "family": "naive", "quantiles": {"p": [0, 1], "strength": [2, 1]}}))
    assert f"--config {bad}: quantiles.strength must be non-decreasing" in err(["--config", str(bad)])
    blur = tmp_path / "blur.json"
    blur.write_text(json.dumps({"kind": "blur2d", "sigma": 2}))
    assert "blur2d blurs rendered frames, not a scene" in err(["--config", str(blur)])
    assert not (tmp_path / "o.ply").exists()
