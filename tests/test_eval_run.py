"""`morphgs eval --run RUN --data DIR`: a refiner trained for real steps on a tiny curated folder,
scored on its test split, input (corrupted) and output (refined) against the clean clips."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import cli, media, metrics
from morphgs.data import load_records
from morphgs.training import train

TINY_MODEL = {"channels": [8, 8, 16, 16], "blocks": [1, 1, 1, 1], "attention_heads": 0, "groups": 4}


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("evalrun")
    morphgs.curate(out=root / "data", pairs_per_scene=2, frames=6, resolution=(64, 32), builtin_scenes=2,
                   builtin_gaussians=20_000, depth=True, test_fraction=0.5, progress=False)
    train(root / "data", out=root / "run", progress=False,
          overrides={"model": TINY_MODEL, "data": {"frames": 6, "size": [32, 64], "num_workers": 0},
                     "optim": {"max_steps": 2}, "run": {"validate_every": 0, "mixed_precision": "no"}})
    return root / "run", root / "data"


def test_eval_run_scores_input_and_output_of_the_test_split(trained: tuple[Path, Path], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    run, data = trained
    out = tmp_path / "eval"
    assert cli.main(["eval", "--run", str(run), "--data", str(data), "--out", str(out), "--quiet",
                     "--metrics", "psnr,ssim,eflow", "--save-refined"]) == 0
    printed = capsys.readouterr().out
    assert "| input |" in printed and "| output |" in printed
    tests = [r for r in load_records(data) if r.split == "test"]
    assert tests
    with open(out / "per_frame.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * sum(r.frames for r in tests)
    for rec in tests:
        clean, corrupted = media.read_clip(rec.clean), media.read_clip(rec.corrupted)
        inp = [row for row in rows if row["clip"] == rec.pair_id and row["label"] == "input"]
        np.testing.assert_allclose([float(r["psnr"]) for r in inp], metrics.psnr(corrupted, clean, reduction="none"))
        refined = media.read_clip(out / "refined" / rec.pair_id / "refined")      # saved as 8-bit PNG
        outp = [row for row in rows if row["clip"] == rec.pair_id and row["label"] == "output"]
        np.testing.assert_allclose([float(r["psnr"]) for r in outp], metrics.psnr(refined, clean, reduction="none"),
                                   atol=0.05)
        assert outp[0]["eflow"] == "" and all(float(r["eflow"]) >= 0 for r in outp[1:])
    assert (out / "summary.md").read_text().count("| input |") == 1 + len(tests)


def test_eval_modes_do_not_mix(trained: tuple[Path, Path], tmp_path: Path) -> None:
    run, data = trained
    for argv in (["--run", str(run)], ["--run", str(run), "--data", str(data), "a", "b"], []):
        with pytest.raises(SystemExit, match="PRED"):
            cli.main(["eval", *argv, "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="takes depth and cameras from the curated folder"):
        cli.main(["eval", "--run", str(run), "--data", str(data), "--cameras", "c.json", "--out", str(tmp_path)])


def test_colour_correction_hands_the_output_the_inputs_colour_shift(trained: tuple[Path, Path], tmp_path: Path) -> None:
    """refine's default Reinhard transfer matches the output's colour statistics to the corrupted
    input's, so the two colour shifts agree; --no-color-correct scores the model's own colours."""
    run, data = trained

    def shifts(*extra: str) -> dict[str, float]:
        out = tmp_path / ("nocc" if extra else "cc")
        assert cli.main(["eval", "--run", str(run), "--data", str(data), "--out", str(out), "--quiet",
                         "--metrics", "color_shift", "--no-plots", *extra]) == 0
        import json

        overall = json.loads((out / "summary.json").read_text())["overall"]
        return {k: overall[k]["color_shift"] for k in ("input", "output")}

    cc = shifts()
    assert cc["output"] == pytest.approx(cc["input"], abs=0.15)
    raw = shifts("--no-color-correct")
    assert raw["input"] == cc["input"] and abs(raw["output"] - cc["output"]) > 0.05
    with pytest.raises(SystemExit, match="applies to --run"):
        cli.main(["eval", "a", "b", "--no-color-correct", "--out", str(tmp_path / "x")])
