"""`morphgs sample` and `morphgs info`, in process and through the installed entry point."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import cli, synthetic


def test_sample_writes_the_synthetic_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s.ply"
    assert cli.main(["sample", str(out), "--gaussians", "5000", "--sh-degree", "2", "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "5,000 Gaussians" in printed and "SH degree 2" in printed
    loaded = morphgs.load(out)
    expected = synthetic.scene(5000, sh_degree=2, seed=3)
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest"):
        np.testing.assert_array_equal(getattr(loaded, f), getattr(expected, f))


@pytest.mark.parametrize("text,count", [("200k", 200_000), ("1_500", 1500), ("2M", 2_000_000),
                                         ("1.5k", 1500)])
def test_gaussian_counts_accept_suffixes(text: str, count: int) -> None:
    from morphgs.commands.sample import _count

    assert _count(text) == count


def test_sample_rejects_a_bad_count(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(["sample", "x.ply", "--gaussians", "lots"])
    assert info.value.code == 2
    assert "not a Gaussian count" in capsys.readouterr().err


def test_info_summarises_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = synthetic.scene(3000, sh_degree=3, seed=1)
    morphgs.save_ply(scene, tmp_path / "s.ply")
    assert cli.main(["info", str(tmp_path / "s.ply")]) == 0
    text = capsys.readouterr().out
    assert "3,000" in text and "sh degree : 3" in text and "bounds" in text and "opacity" in text
    assert cli.main(["info", "--json", str(tmp_path / "s.ply")]) == 0
    s = json.loads(capsys.readouterr().out)
    lo, hi = scene.bounds()
    assert s["gaussians"] == 3000 and s["sh_degree"] == 3
    np.testing.assert_allclose(s["bounds_min"], lo)
    np.testing.assert_allclose(s["bounds_max"], hi)
    assert s["opacity"]["median"] == pytest.approx(float(np.median(scene.opacities)), rel=1e-5)
    assert s["scale"]["max"] == pytest.approx(float(scene.scales.max()), rel=1e-5)


def test_info_lists_extras_of_a_fixture(fixtures_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["info", "--json", str(fixtures_dir / "splatapult_test.ply")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["gaussians"] == 16 and s["extras"] == []


def test_info_on_a_bad_file_reports_the_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a scene at all")
    assert cli.main(["info", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "morphgs info: error" in err and str(bad) in err
    assert cli.main(["info", str(tmp_path / "missing.ply")]) == 1
    assert "No such file" in capsys.readouterr().err


def test_info_on_an_empty_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    morphgs.save_ply(synthetic.scene(0), tmp_path / "e.ply")
    assert cli.main(["info", "--json", str(tmp_path / "e.ply")]) == 0
    assert json.loads(capsys.readouterr().out)["gaussians"] == 0


def test_module_entry_point_runs_in_a_fresh_process(tmp_path: Path) -> None:
    out = tmp_path / "p.ply"
    run = subprocess.run([sys.executable, "-m", "morphgs.cli", "sample", str(out), "-n", "1k"],
                         capture_output=True, text=True, check=True)
    assert "1,000 Gaussians" in run.stdout
    info = subprocess.run([sys.executable, "-m", "morphgs.cli", "info", str(out)],
                          capture_output=True, text=True, check=True)
    assert "1,000" in info.stdout


def test_info_reads_a_fit_run_folder_like_curate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a `morphgs fit` run folder: the highest iteration wins, as in `morphgs curate RUN`
    run = tmp_path / "run"
    for it, n in ((7000, 1000), (30000, 2500)):
        (run / "point_cloud" / f"iteration_{it}").mkdir(parents=True)
        morphgs.save_ply(synthetic.scene(n, sh_degree=1, seed=it),
                         run / "point_cloud" / f"iteration_{it}" / "point_cloud.ply")
    assert cli.main(["info", "--json", str(run)]) == 0
    assert json.loads(capsys.readouterr().out)["gaussians"] == 2500
    assert cli.main(["info", str(run)]) == 0
    assert "iteration_30000" in capsys.readouterr().out
    (tmp_path / "empty").mkdir()
    assert cli.main(["info", str(tmp_path / "empty")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "morphgs info: error" in err and "no scene file" in err
