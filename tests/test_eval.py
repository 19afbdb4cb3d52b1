"""`morphgs.evaluation.evaluate` and `morphgs eval PRED GT`: files, values, layouts, bad input."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from metrics_data import guitar_pair
from PIL import Image

from morphgs import cli, media, metrics
from morphgs.evaluation import ClipPair, EvalError, discover_pairs, evaluate


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A rendered pair on disk as curation writes it: PNG frames, depth and alpha EXRs, cameras.json."""
    d = tmp_path_factory.mktemp("pair")
    pair = guitar_pair()
    pair.save(d)
    (d / "cameras.json").write_text(json.dumps(pair.cameras.to_dict()))
    return d


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_evaluate_arrays_writes_csv_markdown_json_and_plots(tmp_path: Path) -> None:
    pair = guitar_pair()
    pred = np.rint(np.clip(pair.corrupted.rgb, 0, 1) * 255).astype(np.uint8)
    gt = np.rint(np.clip(pair.clean.rgb, 0, 1) * 255).astype(np.uint8)
    report = evaluate([ClipPair("guitar", pred, gt), ClipPair("same", gt, gt)],
                      metrics=("psnr", "ssim", "eflow", "ewarp"), out_dir=tmp_path, progress=False)
    assert report.metrics == ["psnr", "ssim", "eflow", "ewarp"]
    rows = _read_csv(tmp_path / "per_frame.csv")
    assert len(rows) == 2 * len(gt) and rows[0].keys() >= {"label", "clip", "frame", "psnr", "eflow"}
    guitar = [r for r in rows if r["clip"] == "guitar"]
    np.testing.assert_allclose([float(r["psnr"]) for r in guitar], metrics.psnr(pred, gt, reduction="none"))
    np.testing.assert_allclose([float(r["ssim"]) for r in guitar], metrics.ssim(pred, gt, reduction="none"))
    assert guitar[0]["eflow"] == "" and all(r["eflow"] != "" for r in guitar[1:])     # pairs land on frame t
    np.testing.assert_allclose([float(r["eflow"]) for r in guitar[1:]], metrics.flow_epe(pred, gt, reduction="none"))
    same = [r for r in rows if r["clip"] == "same"]
    assert all(r["psnr"] == "inf" for r in same) and all(float(r["eflow"]) == 0.0 for r in same[1:])
    # overall: the mean over every frame of both clips
    psnr_guitar = metrics.psnr(pred, gt)
    assert report.clips[0]["psnr"] == pytest.approx(psnr_guitar)
    assert report.overall["pred"]["ssim"] == pytest.approx(np.mean([float(r["ssim"]) for r in rows]))
    md = (tmp_path / "summary.md").read_text()
    assert "| PSNR ↑ | SSIM ↑ | E_flow ↓ | E_warp ↓ |" in md and "| guitar | 4 |" in md and "∞" in md
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["clips"][1]["psnr"] == "inf" and summary["overall"]["pred"]["psnr"] == "inf"
    for p in report.files["plots"]:
        with Image.open(p) as im:
            assert im.size[0] > 300 and im.size[1] > 200
    assert sorted(p.name for p in report.files["plots"]) == ["guitar.png", "same.png"]


def test_cli_eval_of_a_rendered_pair_with_depth_and_cameras(pair_dir: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "eval"
    rc = cli.main(["eval", str(pair_dir / "corrupted"), str(pair_dir / "clean"), "--out", str(out),
                   "--depth-pred", str(pair_dir / "corrupted"), "--depth-gt", str(pair_dir / "clean"),
                   "--cameras", str(pair_dir / "cameras.json"), "--name", "guitar"])
    assert rc == 0
    printed = capsys.readouterr()
    assert "LPIPS (alex) ↓" in printed.out and "AbsRel ↓" in printed.out and "wrote" in printed.out
    assert "eval" in printed.err                                           # the progress bar
    rows = _read_csv(out / "per_frame.csv")
    assert [r["clip"] for r in rows] == ["guitar"] * 4
    pair = guitar_pair()
    clean_depth, corrupted_depth = pair.clean.depth, pair.corrupted.depth
    ref = metrics.depth_metrics(corrupted_depth, clean_depth, reduction="none")
    np.testing.assert_allclose([float(r["depth_abs_rel"]) for r in rows], ref["abs_rel"], rtol=1e-6)
    # the flow reference is the exact geometric flow of the clean render
    frames = [media.read_clip(pair_dir / s) for s in ("corrupted", "clean")]
    flows, valid = metrics.geometric_flows(media.read_depth(sorted((pair_dir / "clean").glob("*.depth.exr"))),
                                           pair.cameras)
    expected = metrics.flow_epe(frames[0], frames[1], target_flow=flows, valid=valid, reduction="none")
    np.testing.assert_allclose([float(r["eflow"]) for r in rows[1:]], expected)
    assert 0 < float(rows[0]["lpips"]) < 1
    assert (out / "plots" / "guitar.png").is_file()


def test_folders_of_clips_are_matched_by_relative_path(pair_dir: Path, tmp_path: Path) -> None:
    frames = media.read_clip(pair_dir / "clean")
    pred_root, gt_root = tmp_path / "pred", tmp_path / "gt"
    media.write_frames(gt_root / "scene" / "a", frames)
    media.write_video(gt_root / "b.mp4", frames)
    media.write_video(pred_root / "scene" / "a.mp4", frames)          # a video against a frame folder
    media.write_frames(pred_root / "b", frames)
    pairs = discover_pairs(pred_root, gt_root)
    assert [p.name for p in pairs] == ["b", "scene/a"]
    report = evaluate(pairs, metrics=("psnr",), out_dir=tmp_path / "out", progress=False)
    assert [c["clip"] for c in report.clips] == ["b", "scene/a"]
    assert all(c["psnr"] > 35 for c in report.clips)                  # H.264 at crf 18 against the PNGs
    assert sorted(p.name for p in report.files["plots"]) == ["b.png", "scene__a.png"]


def test_bad_input_is_a_clear_error(pair_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frames = media.read_clip(pair_dir / "clean")
    media.write_frames(tmp_path / "short", frames[:3])
    media.write_frames(tmp_path / "small", frames[:, :32, :48])
    (tmp_path / "empty").mkdir()

    def fails(*argv: str) -> str:
        assert cli.main(["eval", *argv, "--out", str(tmp_path / "o"), "--quiet", "--metrics", "psnr"]) == 1
        return capsys.readouterr().err

    clean = str(pair_dir / "clean")
    err = fails(str(tmp_path / "short"), clean)
    assert "pred has 3 frames of 96x64 but gt has 4 frames of 96x64" in err and "short" in err
    assert "48x32" in fails(str(tmp_path / "small"), clean)
    assert "empty: no frames (.png, .jpg) or clips in this folder" in fails(str(tmp_path / "empty"), clean)
    assert "no such file or folder" in fails(str(tmp_path / "nope"), clean)
    media.write_frames(tmp_path / "tree_gt" / "x", frames)
    media.write_frames(tmp_path / "tree_gt" / "y", frames)
    media.write_frames(tmp_path / "tree_pred" / "x", frames)
    assert "no prediction for 1 GT clip(s) (y)" in fails(str(tmp_path / "tree_pred"), str(tmp_path / "tree_gt"))
    (tmp_path / "nothing").mkdir()
    assert "no clips" in fails(str(tmp_path / "nothing"), str(tmp_path / "nothing"))
    with pytest.raises(EvalError, match="unknown metric 'fid'"):
        evaluate([ClipPair("a", frames, frames)], metrics=("fid",))
    with pytest.raises(EvalError, match="no clip pairs"):
        evaluate([], metrics=("psnr",), progress=False)
