"""`morphgs.fit.fit` end to end on a small known scene fitted from its own renders."""

from __future__ import annotations

import csv
import signal
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import morphgs
from fit_helpers import make_dataset, small_config
from morphgs.fit import FitConfig, FitPastError, FitRunError, fit


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root, _, _ = make_dataset(tmp_path_factory.mktemp("fitdata") / "room", points=1500)
    return root


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_fit_from_own_renders_reaches_25db_held_out_in_400_steps(dataset: Path, tmp_path: Path) -> None:
    res = fit(dataset, tmp_path / "run", config=small_config(400), init="points", progress=False)
    # 24 views, every 8th held out: views 0, 8, 16
    assert res.heldout_views == [0, 8, 16] and len(res.train_views) == 21
    assert res.steps == 400
    assert res.heldout_psnr is not None and res.heldout_psnr >= 25.0, res.heldout_psnr
    ev = _rows(res.run_dir / "eval.csv")
    assert [int(r["step"]) for r in ev] == [100, 200, 300, 400]
    psnrs = [float(r["psnr"]) for r in ev]
    assert psnrs[-1] > psnrs[0] + 2.0
    assert float(ev[-1]["psnr"]) == pytest.approx(res.heldout_psnr, abs=1e-9)
    # densification ran: the Gaussian count grew from the 1500 points
    loss = _rows(res.run_dir / "loss.csv")
    assert [int(r["step"]) for r in loss] == list(range(1, 401))
    assert int(loss[-1]["gaussians"]) == res.gaussians > 1500
    assert any(r["reset"] == "1" for r in loss) and any(int(r["split"]) > 0 for r in loss)
    # the PLY in the INRIA layout loads back to the trained scene
    back = morphgs.load(res.ply)
    assert len(back) == res.gaussians and back.sh_degree == 1
    np.testing.assert_array_equal(np.asarray(back.means), np.asarray(res.scene.means))
    assert res.ply == res.run_dir / "point_cloud" / "iteration_400" / "point_cloud.ply"
    views = json.loads((res.run_dir / "views.json").read_text())
    assert [v["index"] for v in views["heldout"]] == [0, 8, 16]
    assert views["heldout"][1]["name"] == "frame_00008.png"
    cfg = FitConfig.load(res.run_dir / "config.toml")
    assert cfg.steps == 400 and cfg.default.refine_every == 50 and cfg.default.opacity_reset
    assert (res.run_dir / "previews" / "step_000400.png").is_file() and (res.run_dir / "preview.png").is_file()
    cams = json.loads((res.run_dir / "cameras.json").read_text())
    assert len(cams) == 24 and cams[0]["width"] == 64
    summary = json.loads((res.run_dir / "fit.json").read_text())
    assert summary["steps"] == 400 and summary["gaussians"] == res.gaussians


def test_a_finished_run_is_not_redone_and_another_config_is_refused(dataset: Path, tmp_path: Path) -> None:
    cfg = small_config(120)
    a = fit(dataset, tmp_path / "run", config=cfg, init="points", progress=False)
    b = fit(dataset, tmp_path / "run", config=cfg, init="points", progress=False)
    assert b.summary["steps_this_call"] == 0 and b.ply.read_bytes() == a.ply.read_bytes()
    with pytest.raises(FitRunError, match="another config"):
        fit(dataset, tmp_path / "run", config=small_config(130), init="points", progress=False)
    c = fit(dataset, tmp_path / "run", config=small_config(130), init="points", progress=False, resume=False)
    assert c.steps == 130


def test_a_stopped_run_resumes_to_the_same_scene_and_rows(dataset: Path, tmp_path: Path) -> None:
    cfg = small_config(250, "mcmc")
    straight = fit(dataset, tmp_path / "a", config=cfg, init="random", progress=False)

    def stop_at_130(kind: str, payload: object) -> bool:
        return kind == "steps" and any(r["step"] >= 130 for r in payload)  # type: ignore[union-attr]

    part = fit(dataset, tmp_path / "b", config=cfg, init="random", progress=False, callback=stop_at_130)
    assert 130 <= part.steps < 250 and not (tmp_path / "b" / "fit.json").exists()
    done = fit(dataset, tmp_path / "b", config=cfg, init="random", progress=False)
    assert done.ply.read_bytes() == straight.ply.read_bytes()
    keys = ["step", "view", "loss", "psnr", "gaussians"]
    ra, rb = _rows(straight.run_dir / "loss.csv"), _rows(done.run_dir / "loss.csv")
    assert [[r[k] for k in keys] for r in ra] == [[r[k] for k in keys] for r in rb]
    assert _rows(straight.run_dir / "eval.csv") == _rows(done.run_dir / "eval.csv")


def test_until_stops_at_the_full_schedules_state_and_resumes_to_the_same_bytes(dataset: Path, tmp_path: Path) -> None:
    """`until=S` (what curate's underfit:F uses) keeps the schedule of the full fit: its state at
    S is that of the full run (a resume from it ends on the uninterrupted run's bytes), not that
    of an S-step schedule; a run already past S refuses it."""
    cfg = small_config(120, "mcmc")
    straight = fit(dataset, tmp_path / "a", config=cfg, init="random", progress=False)
    part = fit(dataset, tmp_path / "b", config=cfg, init="random", progress=False, until=70)
    assert part.steps == 70 and part.ply == tmp_path / "b" / "point_cloud" / "iteration_70" / "point_cloud.ply"
    assert part.ply.is_file() and not (tmp_path / "b" / "fit.json").exists() and part.heldout_psnr is not None
    short = fit(dataset, tmp_path / "c", config=small_config(70, "mcmc"), init="random", progress=False)
    assert short.ply.read_bytes() != part.ply.read_bytes()  # another schedule (the position lr decays faster)
    done = fit(dataset, tmp_path / "b", config=cfg, init="random", progress=False)
    assert done.steps == 120 and done.ply.read_bytes() == straight.ply.read_bytes()
    with pytest.raises(FitPastError, match="at step 120, past the step asked for \\(70\\)"):
        fit(dataset, tmp_path / "b", config=cfg, init="random", progress=False, until=70)
    with pytest.raises(morphgs.MorphgsError, match="until must be in"):
        fit(dataset, tmp_path / "d", config=cfg, init="random", progress=False, until=121)


def test_views_every_k_trains_on_every_kth_view_of_the_trajectory(dataset: Path, tmp_path: Path) -> None:
    res = fit(dataset, tmp_path / "run", config=small_config(30), views="every:4", init="random:500", progress=False)
    traj = [i for i in range(24) if i % 8]
    assert res.train_views == traj[::4] == [1, 5, 10, 14, 19, 23]
    assert res.heldout_views == [0, 8, 16]
    res = fit(dataset, tmp_path / "run2", config=small_config(30), views="n:3", holdout="none", init="random:500",
              progress=False)
    assert res.train_views == [0, 12, 23] and res.heldout_views == [] and res.heldout_psnr is None


def test_held_out_lpips_is_logged_and_leaves_the_fit_alone(dataset: Path, tmp_path: Path) -> None:
    pytest.importorskip("torch")
    from morphgs.media import read_image
    from morphgs.metrics import lpips

    cfg = small_config(200)
    on = fit(dataset, tmp_path / "on", config={**cfg, "output": {**cfg["output"], "lpips": "alex"}},
             init="points", progress=False)
    off = fit(dataset, tmp_path / "off", config={**cfg, "output": {**cfg["output"], "lpips": "off"}},
              init="points", progress=False)
    # the scorer reads the renders; it never changes what is fitted
    assert on.ply.read_bytes() == off.ply.read_bytes()
    ev = _rows(on.run_dir / "eval.csv")
    assert [int(r["step"]) for r in ev] == [100, 200]
    lp = [float(r["lpips"]) for r in ev]
    assert all(0.0 < v < 1.0 for v in lp) and lp[-1] < lp[0]  # the fit gets perceptually closer
    per_view = _rows(on.run_dir / "eval_views.csv")
    assert len(per_view) == 6 and all(r["lpips"] for r in per_view)
    assert np.mean([float(r["lpips"]) for r in per_view if r["step"] == "200"]) == pytest.approx(lp[-1], rel=1e-12)
    # the final figure is LPIPS of the saved scene's renders against the held-out images
    scene = morphgs.load(on.ply)
    views = json.loads((on.run_dir / "views.json").read_text())
    cams = morphgs.trajectory.from_transforms_json(dataset / "transforms.json")
    ref = [lpips(np.clip(morphgs.render(scene, cams[v["index"]]).rgb, 0, 1), read_image(dataset / "images" / v["name"]))
           for v in views["heldout"]]
    assert on.heldout_lpips == pytest.approx(float(np.mean(ref)), abs=2e-3)
    assert json.loads((on.run_dir / "fit.json").read_text())["heldout_lpips"] == on.heldout_lpips
    assert off.heldout_lpips is None and all(r["lpips"] == "" for r in _rows(off.run_dir / "eval.csv"))


def test_the_dry_run_estimates_gaussian_count_follows_a_real_mcmc_fit(dataset: Path, tmp_path: Path) -> None:
    """`morphgs ablate --dry-run` prices a fit by its mean Gaussian count under the MCMC growth
    schedule (`estimate.mean_gaussians`); that count is the one a real fit logs, step by step
    (loss.csv's `gaussians`), both while it grows and once it is at its cap."""
    from morphgs.ablation.estimate import mean_gaussians

    for cap in (3400, 6000):  # 3000 -> 3150 -> 3307 -> 3472 at steps 100, 150, 200: 3400 is reached, 6000 not
        cfg = small_config(250, "mcmc", mcmc={"refine_start": 50, "refine_every": 50, "cap_max": cap})
        res = fit(dataset, tmp_path / f"c{cap}", config=cfg, init="random", progress=False)
        counts = [int(r["gaussians"]) for r in _rows(res.run_dir / "loss.csv")]
        assert len(counts) == 250 and counts[0] == 3000 and max(counts) == min(cap, 3472)
        est = mean_gaussians(3000, cap, 250, refine_start=50, refine_every=50, refine_stop=25_000)
        assert est == pytest.approx(np.mean(counts), rel=1e-3)
    # the schedule's bounds: growth at the steps strictly between refine_start and refine_stop
    assert mean_gaussians(3000, 6000, 250, refine_start=50, refine_every=50, refine_stop=101) == pytest.approx(
        (100 * 3000 + 150 * 3150) / 250)
    assert mean_gaussians(3000, 6000, 250, refine_start=50, refine_every=50, refine_stop=100) == 3000


@pytest.fixture
def ctrl_c_raises() -> Iterator[None]:
    """SIGINT raising KeyboardInterrupt, as in a terminal (a background `make test &` ignores it)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def test_a_ctrl_c_at_a_batch_of_step_rows_hands_the_batch_over_again_before_the_checkpoint(
        tmp_path: Path, ctrl_c_raises: None) -> None:
    # The race of a Ctrl-C landing as a batch of rows reaches Python: the callback raises before
    # it wrote anything. The native loop must hand that batch over again before the checkpoint
    # the stop writes, or the resumed run starts after rows nobody wrote.
    from fit_helpers import orbit_cameras

    from morphgs import _core, synthetic

    scene = synthetic.scene(800, sh_degree=1, seed=0)
    cams = orbit_cameras(6, (32, 24))
    imgs = list(morphgs.render(scene, cams).to_uint8())
    w2c = np.stack([c.world_to_camera for c in cams]).astype(np.float64)
    K = np.stack([c.K for c in cams]).astype(np.float64)
    cfg = FitConfig.from_dict(small_config(300)).native(1.0)
    trainer = _core.Trainer(synthetic.scene(300, sh_degree=1, seed=1), imgs, w2c, K, config=cfg)
    got: list[list[int]] = []
    checkpoints: list[int] = []
    interrupted: list[int] = []

    def callback(kind: str, payload: Any) -> None:
        if kind == "steps":
            steps = [r["step"] for r in payload]
            if steps and steps[-1] >= 150 and not interrupted:
                interrupted.append(steps[-1])
                signal.raise_signal(signal.SIGINT)  # raises here, before the batch is taken
            got.append(steps)
        elif kind == "checkpoint":
            checkpoints.append(payload["step"])

    with pytest.raises(KeyboardInterrupt):
        trainer.run(300, callback=callback, checkpoint=tmp_path / "ck.bin", checkpoint_every=100,
                    progress_every=1e9)  # one batch per checkpoint: steps 1-100, 101-200
    stop = trainer.step
    assert interrupted == [200] and stop == 200 and checkpoints == [100, 200]
    # every step up to the checkpoint was handed over and acknowledged once, in order
    assert [s for batch in got for s in batch] == list(range(1, stop + 1))


def test_a_ctrl_c_in_the_callback_leaves_each_row_once_and_the_run_resumes_to_the_same_rows(
        dataset: Path, tmp_path: Path, ctrl_c_raises: None) -> None:
    cfg = small_config(300, output={"eval_every": 300, "checkpoint_every": 100, "preview_every": 300,
                                    "progress_every": 1e9})
    straight = fit(dataset, tmp_path / "straight", config=cfg, init="points", progress=False)
    seen: list[int] = []

    def callback(kind: str, payload: Any) -> None:
        if kind == "steps":
            seen.extend(r["step"] for r in payload)
            if seen[-1:] == [200]:
                signal.raise_signal(signal.SIGINT)  # after fit's logger wrote the batch

    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        fit(dataset, run, config=cfg, init="points", progress=False, callback=callback)
    # the batch came again (the native loop cannot know how much of it was written); no row twice
    assert seen == list(range(1, 201))
    assert [int(r["step"]) for r in _rows(run / "loss.csv")] == list(range(1, 201))
    resumed = fit(dataset, run, config=cfg, init="points", progress=False)
    assert resumed.ply.read_bytes() == straight.ply.read_bytes()
    def losses(r: Path) -> list[tuple[str, ...]]:  # the numbers (not the timings)
        return [(x["step"], x["view"], x["loss"], x["psnr"], x["gaussians"]) for x in _rows(r / "loss.csv")]

    assert losses(run) == losses(tmp_path / "straight")
