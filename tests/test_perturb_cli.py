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
