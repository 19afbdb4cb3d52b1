"""Refining clips: window plans and their blending (no seams), shapes and padding, the CLI on a
frames folder, an MP4 and a curated pair, colour correction on by default, and the test-split
iterator `morphgs eval` builds on."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from morphgs import media
from morphgs.cli import main
from morphgs.color import lab_stats
from morphgs.inference import iter_refined_pairs, load_run, refine_clip, window_plan
from morphgs.models import ModelContext, Refiner, create_model
from morphgs.training import train
from train_helpers import SMALL_MODEL, curated, small_overrides


def test_window_plans_cover_the_clip_and_cross_fade() -> None:
    plan = window_plan(40, 16, 4)
    assert [s for s, _ in plan] == [0, 12, 24]
    total = np.zeros(40)
    for s, w in plan:
        total[s:s + 16] += w
    np.testing.assert_allclose(total, 1.0)  # these overlaps sum to one without renormalising
    assert list(plan[1][1][:4]) == pytest.approx([0.2, 0.4, 0.6, 0.8])
    assert plan[0][1][0] == 1.0 and plan[-1][1][-1] == 1.0  # clip ends are not faded
    last = window_plan(45, 16, 4)
    assert [s for s, _ in last] == [0, 12, 24, 29]  # the last window ends at the clip's end
    assert [s for s, _ in window_plan(10, 16, 4)] == [0] and len(window_plan(10, 16, 4)[0][1]) == 10
    with pytest.raises(ValueError, match="overlap"):
        window_plan(10, 4, 4)


def test_an_identity_model_returns_the_clip_whatever_the_windows_and_size() -> None:
    torch.manual_seed(0)
    model = create_model("tiny", SMALL_MODEL, ModelContext(frames=6)).eval()  # identity at init
    frames = np.random.default_rng(0).integers(0, 256, (23, 21, 30, 3), dtype=np.uint8)  # 21x30: not multiples of 4
    for window, overlap in ((6, 2), (5, 0), (32, None)):
        out = refine_clip(model, frames, window=window, overlap=overlap, color_correct=False)
        assert out.shape == frames.shape and out.dtype == np.float32
        np.testing.assert_allclose(out, frames / 255.0, atol=1e-6)


class _WindowOffset(Refiner):
    """Adds a different constant on every call, like a model whose windows disagree."""

    def __init__(self) -> None:
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(()))
        self.calls = 0
        self.window = 8

    def refine(self, corrupted: torch.Tensor, **kw: Any) -> torch.Tensor:
        self.calls += 1
        return corrupted * 0 + (-1.0 + 0.5 * (self.calls % 2))  # alternately 0 and 0.25 in [0, 1]


def test_disagreeing_windows_are_blended_without_a_seam() -> None:
    model = _WindowOffset()
    frames = np.zeros((30, 8, 8, 3), np.uint8)
    hard = refine_clip(model, frames, overlap=0, color_correct=False)[:, 0, 0, 0]
    soft = refine_clip(model, frames, overlap=4, color_correct=False)[:, 0, 0, 0]
    assert np.abs(np.diff(hard)).max() == pytest.approx(0.25)  # cut windows jump by the disagreement
    assert np.abs(np.diff(soft)).max() <= 0.25 / 5 + 1e-6  # blended: steps of disagreement / (overlap + 1)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("refine")
    data = curated(root / "data", frames=10, resolution=(40, 32))
    train(data, out=root / "run", overrides=small_overrides(optim={"max_steps": 4}), progress=False)
    return root / "run", data


def _tinted(frames: np.ndarray) -> np.ndarray:
    return np.clip(frames * np.array([0.7, 0.9, 1.2]) + 20, 0, 255).astype(np.uint8)


def test_cli_refines_a_curated_pair_a_frames_folder_and_a_video(trained: tuple[Path, Path], tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    run, data = trained
    pair = next(p for p in (data / "pairs").glob("*/*/*") if (p / "cameras.json").is_file())
    assert main(["refine", str(run), str(pair), "--out", str(tmp_path / "a"), "--video", "--window", "4"]) == 0
    printed = capsys.readouterr().out
    assert "vs clean: PSNR" in printed and "10 refined frames" in printed
    report = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert report["frames"] == 10 and f"{report['psnr_refined']:.2f} dB" in printed
    assert (tmp_path / "a" / "preview.png").is_file()  # before / after / target strip
    out = media.read_clip(tmp_path / "a" / "frames")
    assert out.shape == (10, 32, 40, 3) and media.clip_info(tmp_path / "a" / "refined.mp4") == (10, 32, 40)
    # an MP4 input gives as many frames as it has
    video = media.write_video(tmp_path / "in.mp4", media.read_clip(pair / "corrupted"))
    assert main(["refine", str(run), str(video), "--out", str(tmp_path / "b")]) == 0
    assert media.read_clip(tmp_path / "b" / "frames").shape == (10, 32, 40, 3)
    # colour correction is on by default and matches --color-ref's statistics; off, it does not
    (tmp_path / "tint").mkdir()
    tint = _tinted(media.read_clip(pair / "clean"))
    media.write_frames(tmp_path / "tint", tint)
    assert main(["refine", str(run), str(pair / "corrupted"), "--out", str(tmp_path / "c"),
                 "--color-ref", str(tmp_path / "tint")]) == 0
    assert main(["refine", str(run), str(pair / "corrupted"), "--out", str(tmp_path / "d"), "--no-color-correct"]) == 0
    m_ref, s_ref = lab_stats(tint)
    m_c, s_c = lab_stats(media.read_clip(tmp_path / "c" / "frames"))
    m_d, _ = lab_stats(media.read_clip(tmp_path / "d" / "frames"))
    np.testing.assert_allclose(m_c, m_ref, atol=1.0)
    np.testing.assert_allclose(s_c, s_ref, rtol=0.1, atol=1.0)
    assert np.abs(m_d - m_ref).max() > 3.0


def test_cli_refine_errors_name_the_path(trained: tuple[Path, Path], tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    run, _ = trained
    assert main(["refine", str(run), str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 1
    assert "missing" in capsys.readouterr().err
    assert main(["refine", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "o")]) == 1
    assert "not a run folder" in capsys.readouterr().err


def test_test_pairs_are_refined_for_evaluation(trained: tuple[Path, Path], tmp_path: Path) -> None:
    run, data = trained
    loaded = load_run(run)
    assert loaded.step == 4 and loaded.config.model == "tiny"
    got = list(iter_refined_pairs(loaded, data, split="test", out=tmp_path, window=4))
    assert [g.pair_id for g in got] == ["sample-0/morphological/0000", "sample-0/morphological/0001"]
    for g in got:
        assert g.refined.shape == g.clean.shape == g.corrupted.shape == (10, 32, 40, 3)
        assert len(media.frame_paths(tmp_path / g.pair_id / "refined")) == 10
