"""The fit across processes: the same bytes for 1 and 2 threads, and resume after a real
SIGKILL or Ctrl-C (SIGINT) giving the same bytes as an uninterrupted run."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fit_helpers import make_dataset, small_config

# The child: fit DATA into RUN with CONFIG (JSON); SLOW seconds of sleep per callback batch keep
# it running long enough to be killed mid-run (sleeping changes no number).
CHILD = """
import json, sys, time
from morphgs.fit import fit
data, run, cfg, init, slow = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), sys.argv[4], float(sys.argv[5])
cb = (lambda kind, payload: time.sleep(slow)) if slow > 0 else None
res = fit(data, run, config=cfg, init=init, progress=False, callback=cb)
print(json.dumps({"steps": res.steps, "ply": str(res.ply)}))
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root, _, _ = make_dataset(tmp_path_factory.mktemp("fitproc") / "room", views=16, points=800)
    return root


def _start(dataset: Path, run: Path, cfg: dict, init: str, *, threads: int = 2, slow: float = 0.0) -> subprocess.Popen:
    env = dict(os.environ, MORPHGS_NUM_THREADS=str(threads))
    env.pop("RAYON_NUM_THREADS", None)
    return subprocess.Popen([sys.executable, "-c", CHILD, str(dataset), str(run), json.dumps(cfg), init, str(slow)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(p: subprocess.Popen) -> dict:
    out, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def _losses(run: Path) -> list[tuple[str, ...]]:
    with open(run / "loss.csv", encoding="utf-8") as f:
        return [(r["step"], r["view"], r["loss"], r["psnr"], r["gaussians"]) for r in csv.DictReader(f)]


@pytest.mark.parametrize("strategy,init", [("default", "points"), ("mcmc", "random")])
def test_one_and_two_threads_give_the_same_bytes(dataset: Path, tmp_path: Path, strategy: str, init: str) -> None:
    cfg = small_config(220, strategy)
    one = _finish(_start(dataset, tmp_path / "t1", cfg, init, threads=1))
    two = _finish(_start(dataset, tmp_path / "t2", cfg, init, threads=2))
    assert Path(one["ply"]).read_bytes() == Path(two["ply"]).read_bytes()
    assert _losses(tmp_path / "t1") == _losses(tmp_path / "t2")
    assert (tmp_path / "t1" / "eval.csv").read_bytes() == (tmp_path / "t2" / "eval.csv").read_bytes()


def _wait_for_checkpoint_and_rows(run: Path, p: subprocess.Popen, rows_past: int) -> None:
    """Until checkpoint.bin exists and loss.csv holds rows past the first checkpoint."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        assert p.poll() is None, "the child finished before it could be stopped"
        ck = run / "checkpoint.bin"
        if ck.is_file() and (run / "loss.csv").is_file():
            with open(run / "loss.csv", encoding="utf-8") as f:
                n = sum(1 for _ in f) - 1
            if n >= rows_past:
                return
        time.sleep(0.01)
    raise AssertionError("no checkpoint appeared")


def test_resume_after_sigkill_gives_the_same_bytes(dataset: Path, tmp_path: Path) -> None:
    cfg = small_config(300, "default")
    straight = _finish(_start(dataset, tmp_path / "straight", cfg, "points"))
    run = tmp_path / "killed"
    p = _start(dataset, run, cfg, "points", slow=0.02)
    _wait_for_checkpoint_and_rows(run, p, 140)  # the checkpoint at 100 and rows beyond it
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL
    assert not (run / "fit.json").exists()
    resumed = _finish(_start(dataset, run, cfg, "points"))
    assert Path(resumed["ply"]).read_bytes() == Path(straight["ply"]).read_bytes()
    assert _losses(run) == _losses(tmp_path / "straight")
    assert (run / "eval.csv").read_bytes() == (tmp_path / "straight" / "eval.csv").read_bytes()


def test_ctrl_c_writes_a_checkpoint_and_the_run_resumes(dataset: Path, tmp_path: Path) -> None:
    # The CLI child cannot be slowed down, and the first sign of progress it leaves is the
    # checkpoint at step 100, so the run outlasts it by 900 steps (over a second at 600+
    # steps/s); one evaluation, at the end, keeps it cheap.
    steps = 1000
    cfg = small_config(steps, "mcmc", output={"eval_every": steps, "checkpoint_every": 100,
                                               "preview_every": steps, "progress_every": 0.0})
    straight = _finish(_start(dataset, tmp_path / "straight", cfg, "random"))
    run = tmp_path / "interrupted"
    env = dict(os.environ, MORPHGS_NUM_THREADS="2")
    p = subprocess.Popen([sys.executable, "-m", "morphgs.cli", "fit", str(dataset), "--out", str(run), "--config",
                          str(_toml(tmp_path, cfg)), "--init", "random", "--no-progress"],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=_ctrl_c_as_in_a_terminal)
    _wait_for_checkpoint_and_rows(run, p, 10)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "rerun the same command to resume" in err
    # the interrupt wrote a checkpoint at the step it stopped at (rows never run ahead of it)
    rows = _losses(run)
    assert 0 < len(rows) < steps
    resumed = _finish(_start(dataset, run, cfg, "random"))
    assert Path(resumed["ply"]).read_bytes() == Path(straight["ply"]).read_bytes()
    assert _losses(run) == _losses(tmp_path / "straight")


def _ctrl_c_as_in_a_terminal() -> None:
    """SIGINT's default action in the child, as a terminal's foreground job has it: pytest run as a
    background job of a non-interactive shell (`nohup make test &`) ignores SIGINT, children
    inherit that, and Python then never raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _toml(tmp: Path, cfg: dict) -> Path:
    from morphgs.fit import FitConfig

    path = tmp / "cfg.toml"
    path.write_text(FitConfig.from_dict(cfg).to_toml(), encoding="utf-8")
    return path
