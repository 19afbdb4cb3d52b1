"""The training loop for real: a 2-pair overfit, the run folder, resume after a SIGKILL giving
the same next losses, two processes training like one with twice the batch, live pairs, and
config and folder errors."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from morphgs.cli import main
from morphgs.configfile import ConfigError
from morphgs.models import UnknownModelError
from morphgs.training import TrainingError, latest_checkpoint, train
from morphgs.training.logs import CsvLog
from morphgs.training.schedule import lr_factor
from train_helpers import curated, small_overrides

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return curated(tmp_path_factory.mktemp("loop") / "ds", frames=8, resolution=(48, 40))


@pytest.fixture(scope="module")
def two_pairs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two train pairs (one per built-in scene), no test split."""
    return curated(tmp_path_factory.mktemp("two") / "ds", pairs_per_scene=1, frames=4, resolution=(32, 32),
                   test_fraction=0.0)


def _losses(run: Path) -> list[tuple[int, str, str]]:
    return [(int(r["step"]), r["loss"], r["l1"]) for r in CsvLog(run / "logs" / "train.csv").read()]


def _cli(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "morphgs", "train", "--no-progress", *args]


def _sets(overrides: dict[str, dict[str, object]]) -> list[str]:
    out = []
    for section, values in overrides.items():
        for k, v in values.items():
            out += ["--set", f"{section}.{k}={json.dumps(v)}"]
    return out


def test_a_two_pair_dataset_is_overfit(two_pairs: Path, tmp_path: Path) -> None:
    over = small_overrides(data={"frames": 4, "size": [32, 32]}, optim={"max_steps": 150, "lr": 3e-3, "warmup": 0.0},
                           run={"checkpoint_every": 0})
    over["model"]["channels"] = [16, 32]  # ~35k parameters
    result = train(two_pairs, out=tmp_path / "run", overrides=over, progress=False)
    losses = [loss for _, loss in result.losses]
    first, last = sum(losses[:5]) / 5, sum(losses[-5:]) / 5
    assert last < first / 3, (first, last)  # stated factor: the loss falls more than 3x


def test_the_run_folder_holds_config_checkpoints_logs_and_previews(data: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "mine.toml"
    text = "# my run\n[optim]\nmax_steps = 6  # short\n\n[data]\nframes = 4\n"
    cfg.write_text(text)
    over = small_overrides(run={"validate_every": 3, "checkpoint_every": 2, "keep_checkpoints": 2})
    del over["optim"]["max_steps"]
    result = train(data, out=tmp_path / "run", config=cfg, overrides=over, progress=False)
    run = tmp_path / "run"
    assert (run / "config.toml").read_text() == text  # as written
    info = json.loads((run / "run.json").read_text())
    assert info["config"]["optim"]["max_steps"] == 6 and info["config"]["model_config"]["channels"] == [8, 16]
    assert info["overrides"]["run"]["validate_every"] == 3 and info["data"] == str(data.resolve())
    assert [p.name for p in sorted((run / "checkpoints").iterdir())] == ["step-0000004", "step-0000006"]
    assert result.checkpoint == run / "checkpoints" / "step-0000006"
    assert {"trained.safetensors", "optimizer.bin", "state.json", "random_states_0.pkl"} <= {
        p.name for p in result.checkpoint.iterdir()}
    rows = CsvLog(run / "logs" / "train.csv").read()
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5, 6]
    assert {"loss", "l1", "l1_input", "ssim", "grad_norm", "lr", "samples_per_s"} <= set(rows[0])
    # the lr column follows the schedule: 5% warmup rounds to 0 steps at 6 steps, then cosine
    for r in rows:
        assert float(r["lr"]) == pytest.approx(2e-3 * lr_factor(int(r["step"]) - 1, warmup_steps=0, total_steps=6,
                                                                   schedule="cosine"))
    val = CsvLog(run / "logs" / "val.csv").read()
    assert [int(r["step"]) for r in val] == [3, 6]
    assert float(val[0]["psnr_input"]) == pytest.approx(result.validation["psnr_input"])
    assert (run / "previews" / "step-0000003.png").is_file() and (run / "previews" / "step-0000006.png").is_file()
    assert list((run / "logs" / "tb").glob("events.out.tfevents.*"))


def test_lr_schedule_warms_up_linearly_then_follows_a_half_cosine() -> None:
    f = [lr_factor(s, warmup_steps=5, total_steps=105, schedule="cosine") for s in range(106)]
    assert f[:6] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert f[55] == pytest.approx(0.5) and f[105] == pytest.approx(0.0)
    assert all(a >= b for a, b in zip(f[5:], f[6:]))
    assert lr_factor(55, warmup_steps=5, total_steps=105, schedule="linear") == pytest.approx(0.5)


def test_resume_after_sigkill_gives_the_same_next_losses(data: Path, tmp_path: Path) -> None:
    over = small_overrides(data={"num_workers": 2, "flip": True}, optim={"max_steps": 60},
                           run={"checkpoint_every": 5, "keep_checkpoints": 3})
    args = ["--data", str(data), *_sets(over)]
    whole = subprocess.run(_cli([*args, "--out", str(tmp_path / "whole")]), env=ENV, capture_output=True, text=True,
                           timeout=600)
    assert whole.returncode == 0, whole.stderr
    run = tmp_path / "killed"
    proc = subprocess.Popen(_cli([*args, "--out", str(run)]), env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while latest_checkpoint(run) is None and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL  # killed mid-run, not finished
    killed_at = int(latest_checkpoint(run).name[5:])  # type: ignore[union-attr]
    assert 5 <= killed_at < 60
    resumed = subprocess.run(_cli(["--out", str(run), "--resume"]), env=ENV, capture_output=True, text=True,
                             timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed {run} at step {killed_at}" in resumed.stderr
    assert _losses(run) == _losses(tmp_path / "whole")  # every step's loss, to the last bit
    a = load_file(str(latest_checkpoint(run) / "trained.safetensors"))  # type: ignore[operator]
    b = load_file(str(latest_checkpoint(tmp_path / "whole") / "trained.safetensors"))  # type: ignore[operator]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_two_processes_train_like_one_process_with_twice_the_batch(two_pairs: Path, tmp_path: Path) -> None:
    over = small_overrides(data={"batch_size": 1}, optim={"max_steps": 4}, run={"checkpoint_every": 0})
    # torchrun starts two gloo processes; accelerate (cpu: no CUDA here) wraps the model in DDP
    launch = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
              str(_free_port()), "-m", "morphgs", "train", "--no-progress", "--data", str(two_pairs), "--out", str(tmp_path / "ddp"),
              *_sets(over)]
    ddp = subprocess.run(launch, env=ENV, capture_output=True, text=True, timeout=600)
    assert ddp.returncode == 0, ddp.stderr[-3000:]
    assert "2 process(es)" in ddp.stderr
    over["data"]["batch_size"] = 2
    one = subprocess.run(_cli(["--data", str(two_pairs), "--out", str(tmp_path / "one"), *_sets(over)]), env=ENV,
                         capture_output=True, text=True, timeout=600)
    assert one.returncode == 0, one.stderr
    assert json.loads((tmp_path / "ddp" / "run.json").read_text())["processes"] == 2
    a = load_file(str(tmp_path / "ddp" / "checkpoints" / "step-0000004" / "trained.safetensors"))
    b = load_file(str(tmp_path / "one" / "checkpoints" / "step-0000004" / "trained.safetensors"))
    from morphgs.models import ModelContext, create_model

    torch.manual_seed(0)  # the loop's initial weights (seed 0)
    init = create_model("tiny", over["model"], ModelContext(frames=4)).trained_state_dict()
    assert max(float((a[k] - init[k]).abs().max()) for k in a) > 1e-3  # training moved the weights
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-5)
    la, lb = _losses(tmp_path / "ddp"), _losses(tmp_path / "one")
    for (sa, loss_a, _), (sb, loss_b, _) in zip(la, lb):
        assert sa == sb and float(loss_a) == pytest.approx(float(loss_b), rel=1e-4)  # the mean over both ranks


def test_two_accumulated_micro_batches_train_like_one_batch_of_two(two_pairs: Path, tmp_path: Path) -> None:
    weights, lrs = [], []
    for name, data_over, optim_over in (("accum", {"batch_size": 1}, {"grad_accum": 2}),
                                        ("batch", {"batch_size": 2}, {"grad_accum": 1})):
        over = small_overrides(data=data_over, optim={"max_steps": 3, **optim_over}, run={"checkpoint_every": 0})
        result = train(two_pairs, out=tmp_path / name, overrides=over, progress=False)
        weights.append(load_file(str(result.checkpoint / "trained.safetensors")))
        lrs.append([float(r["lr"]) for r in CsvLog(tmp_path / name / "logs" / "train.csv").read()])
    assert lrs[0] == lrs[1] and len(lrs[0]) == 3  # one scheduler step per optimizer step, not per micro-batch
    a, b = weights
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-5)


def test_fused_adamw_trains_like_the_per_tensor_update_and_falls_back_where_torch_has_none(
        two_pairs: Path, tmp_path: Path) -> None:
    """`[optim] fused` (the default) takes torch's fused AdamW: the same update in another
    rounding, so three real steps land within float rounding of the per-tensor loop's weights;
    a device torch has no fused kernel for falls back to the loop and says so."""
    from morphgs.training.config import OptimConfig
    from morphgs.training.loop import _adamw

    weights = []
    for fused in (True, False):
        over = small_overrides(optim={"max_steps": 3, "fused": fused}, run={"checkpoint_every": 0})
        result = train(two_pairs, out=tmp_path / f"fused-{fused}", overrides=over, progress=False)
        weights.append(load_file(str(result.checkpoint / "trained.safetensors")))
    assert any(not torch.equal(weights[0][k], weights[1][k]) for k in weights[0])  # it did run fused
    for k in weights[0]:
        torch.testing.assert_close(weights[0][k], weights[1][k], rtol=1e-5, atol=1e-6)
    said: list[str] = []
    p = torch.nn.Parameter(torch.zeros(4, device="meta"))
    opt = _adamw([p], OptimConfig(), said.append)
    assert not opt.defaults.get("fused") and len(said) == 1 and "per-tensor update" in said[0]
    assert _adamw([torch.nn.Parameter(torch.zeros(4))], OptimConfig(), said.append).defaults["fused"]


def test_live_pairs_train_and_validate_on_a_curated_test_split(data: Path, tmp_path: Path) -> None:
    scene = REPO / "tests" / "fixtures" / "marcelpadilla_spot_10k.splat"
    over = small_overrides(data={"live": True, "samples_per_epoch": 4, "live_threads": 1},
                           optim={"max_steps": 3}, run={"validate_every": 3})
    result = train(data, out=tmp_path / "run", overrides=over, scenes=[scene], progress=False)
    assert result.steps == 3 and result.validation["psnr_output"] > 0
    assert json.loads((tmp_path / "run" / "run.json").read_text())["scenes"] == [str(scene)]


# ---- errors ----


def test_config_errors_name_the_file_and_key(data: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[optim]\nlrr = 1.0\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[optim\] unknown key 'lrr' \(known: lr, "):
        train(data, out=tmp_path / "a", config=bad)
    bad.write_text("[data]\nframes = 'many'\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[data\] frames: expected an integer, got 'many'"):
        train(data, out=tmp_path / "a", config=bad)
    bad.write_text("[data\nframes = 2\n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        train(data, out=tmp_path / "a", config=bad)
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        train(data, out=tmp_path / "a", config=tmp_path / "nope.toml")
    with pytest.raises(UnknownModelError, match="unknown model 'huge'"):
        train(data, out=tmp_path / "a", model="huge")
    with pytest.raises(ConfigError, match=r"\[optim\] warmup is a share"):
        train(data, out=tmp_path / "a", overrides={"optim": {"warmup": 2.0}})


def test_run_folder_errors(data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x").write_text("")
    with pytest.raises(TrainingError, match="busy: already exists and is not empty"):
        train(data, out=tmp_path / "busy", overrides=small_overrides())
    with pytest.raises(FileNotFoundError, match="no such run folder"):
        train(data, out=tmp_path / "none", resume=True)
    with pytest.raises(FileNotFoundError, match="missing"):
        train(tmp_path / "missing", out=tmp_path / "r", overrides=small_overrides())
    train(data, out=tmp_path / "r", overrides=small_overrides(optim={"max_steps": 2}), progress=False)
    with pytest.raises(ConfigError, match="resumes with the config it started with"):
        train(data, out=tmp_path / "r", resume=True, overrides={"optim": {"lr": 0.5}})
    # the command line reports the same errors in one line and exits with status 1
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "busy")]) == 1
    assert "already exists" in capsys.readouterr().err
