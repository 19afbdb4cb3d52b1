"""Reliability of the commands that write a folder, through the real CLI in real processes
(docs/reliability.md): one writer per folder (a second `morphgs curate` refused or waiting, a
dead writer's lock taken over, shards side by side), an idempotent manifest, SIGTERM / SIGKILL
at points the test chooses and resume to the same bytes, damaged fit checkpoints, a full disk
(RLIMIT_FSIZE in the child), and a table of damaged inputs where every subcommand ends with one
`morphgs CMD: error: ...` line naming the file and no traceback. Training: test_reliability_train.py."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

import morphgs
from morphgs import MorphgsWarning
from morphgs.curation import manifest
from morphgs.reliability import FolderBusyError, folder_lock

from fit_helpers import make_dataset, small_config

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "MORPHGS_NUM_THREADS": "1"}
ENV.pop("MORPHGS_TRACEBACK", None)

# a curate run long enough (a few seconds) to be caught while it holds its folder
SLOW_CURATE = ["--size", "64x48", "--frames", "24", "-k", "3", "--sample-gaussians", "20000", "--no-progress"]
QUICK_CURATE = ["--size", "32x24", "--frames", "3", "-k", "3", "--sample-gaussians", "2000", "--no-progress"]


def _morphgs(*args: str) -> list[str]:
    return [sys.executable, "-m", "morphgs", *args]


def _run(*args: str, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(_morphgs(*args), env=ENV, capture_output=True, text=True, timeout=300, **kw)  # type: ignore[call-overload]


def _start(*args: str, **kw: object) -> subprocess.Popen[str]:
    return subprocess.Popen(_morphgs(*args), env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            **kw)  # type: ignore[call-overload]


def one_error_line(rc: int, err: str, cmd: str) -> str:
    """The single `morphgs CMD: error: ...` line of a failed command (and no traceback)."""
    assert rc not in (0, None), err
    assert "Traceback" not in err and "DataLoader worker" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"morphgs {cmd}: error: ")]
    assert len(lines) == 1, err
    return lines[0]


def _until(cond, proc: subprocess.Popen[str] | None = None, timeout: float = 120.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not cond():
        assert proc is None or proc.poll() is None, proc.communicate() if proc else ""
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def _holds_lock(folder: Path, name: str = ".morphgs.lock") -> bool:
    p = folder / name
    return p.is_file() and p.stat().st_size > 0


def _lines(path: Path) -> list[dict]:
    return [json.loads(ln) for ln in path.read_text(encoding="utf-8").splitlines()] if path.is_file() else []


def _pair_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / "pairs").rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """QUICK_CURATE, uninterrupted."""
    out = tmp_path_factory.mktemp("ref") / "ds"
    r = _run("curate", "--out", str(out), *QUICK_CURATE)
    assert r.returncode == 0, r.stderr
    return out


# ---- one writer per folder ----

def test_a_second_curate_is_refused_naming_the_first_then_waits_with_wait(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    first = _start("curate", "--out", str(out), *SLOW_CURATE)
    try:
        _until(lambda: _holds_lock(out), first)
        first.send_signal(signal.SIGSTOP)  # hold it there while the second one tries
        second = _run("curate", "--out", str(out), *SLOW_CURATE)
        line = one_error_line(second.returncode, second.stderr, "curate")
        assert f"{out} is being written by another morphgs process (pid {first.pid} on " in line
        assert "started " in line and "--wait" in line
        waiting = _start("curate", "--out", str(out), *SLOW_CURATE, "--wait")
        _until(lambda: "waiting for it to end" in (waiting.stderr.readline() or ""), waiting)  # type: ignore[union-attr]
    finally:
        first.send_signal(signal.SIGCONT)
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    _, err2 = waiting.communicate(timeout=300)
    assert waiting.returncode == 0, err2
    assert "0 pairs made, 6 already done" in err2
    recs = _lines(out / "manifest.jsonl")
    assert len(recs) == 6 and len({r["pair_id"] for r in recs}) == 6


def test_a_dead_writers_lock_is_taken_over_and_the_run_finishes(tmp_path: Path, reference: Path) -> None:
    out = tmp_path / "ds"
    victim = _start("curate", "--out", str(out), *QUICK_CURATE)
    _until(lambda: _holds_lock(out), victim)
    victim.kill()
    victim.communicate(timeout=60)
    again = _run("curate", "--out", str(out), *QUICK_CURATE)
    assert again.returncode == 0, again.stderr
    assert f"took over the lock of {out} left by a process that is gone (pid {victim.pid} on " in again.stderr
    assert _pair_bytes(out) == _pair_bytes(reference)
    assert len({r["pair_id"] for r in _lines(out / "manifest.jsonl")}) == len(_lines(out / "manifest.jsonl")) == 6


def test_shards_write_one_folder_side_by_side_and_an_unsharded_run_is_refused(tmp_path: Path,
                                                                            reference: Path) -> None:
    out = tmp_path / "ds"
    shard0 = _start("curate", "--out", str(out), *QUICK_CURATE, "--shard-index", "0", "--num-shards", "2")
    try:
        _until(lambda: _holds_lock(out, ".morphgs-shard000-of002.lock"), shard0)
        shard0.send_signal(signal.SIGSTOP)
        shard1 = _run("curate", "--out", str(out), *QUICK_CURATE, "--shard-index", "1", "--num-shards", "2")
        assert shard1.returncode == 0, shard1.stderr
        whole = _run("curate", "--out", str(out), *QUICK_CURATE)
        line = one_error_line(whole.returncode, whole.stderr, "curate")
        assert f"shard000-of002: pid {shard0.pid} on " in line
        twin = _run("curate", "--out", str(out), *QUICK_CURATE, "--shard-index", "0", "--num-shards", "2")
        assert f"pid {shard0.pid}" in one_error_line(twin.returncode, twin.stderr, "curate")
    finally:
        shard0.send_signal(signal.SIGCONT)
    _, err = shard0.communicate(timeout=300)
    assert shard0.returncode == 0, err
    assert set(manifest.load(out)) == set(manifest.load(reference))
    assert _pair_bytes(out) == _pair_bytes(reference)


@pytest.mark.parametrize("cmd", ["train", "fit", "export", "calibrate", "fit-many"])
def test_other_commands_refuse_a_folder_another_process_writes(cmd: str, tmp_path: Path, reference: Path) -> None:
    out = tmp_path / "out"
    args = {"train": ["train", "--data", str(reference), "--out", str(out)],
            "fit": ["fit", str(tmp_path / "nodata"), "--out", str(out)],
            "export": ["export", "difix", str(reference), str(out)],
            "calibrate": ["calibrate", "--out", str(out), "--regime", "sparse:4", "--sample-gaussians", "500",
                          "--frames", "2", "--size", "32x24"],
            # several captures: the multi-capture fit, whose output ROOT is locked (a missing
            # capture would only be reported at the end, so the lock is what stops it here)
            "fit-many": ["fit", str(tmp_path / "cap-a"), str(tmp_path / "cap-b"), "--out", str(out)]}[cmd]
    with folder_lock(out, command="test", beside=cmd == "export"):  # this test process is the first writer
        r = _run(*args)
    line = one_error_line(r.returncode, r.stderr, cmd.split("-")[0])
    assert f"is being written by another morphgs process (pid {os.getpid()} on " in line


def test_the_lock_in_process_nests_and_refuses_another_holder(tmp_path: Path) -> None:
    with folder_lock(tmp_path / "a", command="one"):
        with folder_lock(tmp_path / "a", command="nested"):  # the same process again: nests
            pass
        assert _holds_lock(tmp_path / "a")  # still held after the nested release
        code = f"from morphgs.reliability import folder_lock\nwith folder_lock({str(tmp_path / 'a')!r}, command='x'): pass"
        r = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True, timeout=60)
        assert r.returncode != 0 and "FolderBusyError" in r.stderr and f"pid {os.getpid()}" in r.stderr
    assert not _holds_lock(tmp_path / "a")  # a clean release leaves no holder behind
    with pytest.raises(FolderBusyError):  # a process's own lock taken by a second, independent holder
        with folder_lock(tmp_path / "b", command="one", shard=(0, 2)):
            with folder_lock(tmp_path / "b", command="two", shard=(0, 2)):
                pass


# ---- the manifest: one record per pair id ----

def test_duplicate_manifest_lines_are_read_once_with_a_warning_and_a_rerun_rewrites_them(
        tmp_path: Path, reference: Path) -> None:
    import shutil

    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    text = (out / "manifest.jsonl").read_text(encoding="utf-8")
    (out / "manifest.jsonl").write_text(text + text, encoding="utf-8")  # what two unlocked writers left
    with pytest.warns(MorphgsWarning, match="6 pair id\\(s\\) are listed more than once in manifest.jsonl"):
        recs = manifest.load(out)
    assert len(recs) == 6
    r = _run("curate", "--out", str(out), *QUICK_CURATE)
    assert r.returncode == 0, r.stderr
    assert "6 duplicate or unfinished line(s) removed" in r.stderr and "0 pairs made, 6 already done" in r.stderr
    assert (out / "manifest.jsonl").read_text(encoding="utf-8") == text
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(manifest.load(out)) == 6


# ---- preemption: SIGTERM and SIGKILL, then resume ----

@pytest.mark.parametrize("workers", ["1", "2"])
def test_sigterm_stops_curate_keeping_finished_pairs_and_a_rerun_gives_the_same_bytes(
        workers: str, tmp_path: Path, reference: Path) -> None:
    out = tmp_path / "ds"
    p = _start("curate", "--out", str(out), *QUICK_CURATE, "--frames", "3", "-j", workers)
    _until(lambda: _holds_lock(out), p)
    p.send_signal(signal.SIGSTOP)  # a chosen point: lock held, pairs in progress
    p.send_signal(signal.SIGTERM)
    p.send_signal(signal.SIGCONT)
    _, err = p.communicate(timeout=120)
    if p.returncode == 0:  # it finished before the signal was handled: nothing to check
        pytest.skip("the run finished before SIGTERM arrived")
    assert p.returncode == 143, err
    assert "Traceback" not in err
    assert "morphgs curate: stopped by SIGTERM; the finished pairs are kept; rerun the same command to resume" in err
    for rec in _lines(out / "manifest.jsonl"):  # every record is a whole pair
        assert manifest.is_complete(out, rec)
    assert not _holds_lock(out)  # released on the way out
    again = _run("curate", "--out", str(out), *QUICK_CURATE)
    assert again.returncode == 0, again.stderr
    assert "took over" not in again.stderr
    assert _pair_bytes(out) == _pair_bytes(reference)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sigkill_or_sigterm_at_a_random_point_then_a_rerun_gives_the_same_bytes(seed: int, tmp_path: Path,
                                                                              reference: Path) -> None:
    import random

    rnd = random.Random(seed)
    sig = rnd.choice([signal.SIGKILL, signal.SIGTERM])
    out = tmp_path / "ds"
    p = _start("curate", "--out", str(out), *QUICK_CURATE)
    time.sleep(rnd.uniform(0.0, 1.5))  # somewhere between start-up and the end of the run
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert "Traceback" not in err
    # finished, killed, stopped by the handler (143), or terminated by SIGTERM during start-up, before
    # the CLI installs its handler
    assert p.returncode in (0, -signal.SIGKILL, 143, -signal.SIGTERM), err
    for rec in _lines(out / "manifest.jsonl"):
        assert manifest.is_complete(out, rec)
    again = _run("curate", "--out", str(out), *QUICK_CURATE)
    assert again.returncode == 0, again.stderr
    assert _pair_bytes(out) == _pair_bytes(reference)
    assert len(_lines(out / "manifest.jsonl")) == 6


@pytest.fixture(scope="module")
def fit_data(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A tiny posed dataset, a fit config (checkpoints every 20 of 400 steps) and its straight run."""
    from morphgs.fit import FitConfig

    root, _, _ = make_dataset(tmp_path_factory.mktemp("fitrel") / "room", views=8, size=(32, 24), gaussians=1500)
    cfg = small_config(400, "default", output={"eval_every": 0, "checkpoint_every": 20, "preview_every": 0,
                                                "progress_every": 0.0})
    toml = root.parent / "cfg.toml"
    toml.write_text(FitConfig.from_dict(cfg).to_toml(), encoding="utf-8")
    straight = root.parent / "straight"
    r = _run("fit", str(root), "--out", str(straight), "--config", str(toml), "--init", "random", "--no-progress")
    assert r.returncode == 0, r.stderr
    return root, toml, straight


def _fit(fit_data: tuple[Path, Path, Path], run: Path) -> list[str]:
    root, toml, _ = fit_data
    return ["fit", str(root), "--out", str(run), "--config", str(toml), "--init", "random", "--no-progress"]


def _losses(run: Path) -> list[list[str]]:
    """loss.csv without its wall-time column."""
    rows = [ln.split(",") for ln in (run / "loss.csv").read_text(encoding="utf-8").splitlines()]
    return [r[:-1] for r in rows]


def _ply(run: Path) -> bytes:
    return (run / "point_cloud" / "iteration_400" / "point_cloud.ply").read_bytes()


def test_sigterm_stops_fit_with_a_checkpoint_and_the_rerun_gives_the_same_bytes(
        fit_data: tuple[Path, Path, Path], tmp_path: Path) -> None:
    run = tmp_path / "run"
    p = _start(*_fit(fit_data, run))
    _until(lambda: (run / "checkpoint.bin").is_file(), p)
    p.send_signal(signal.SIGSTOP)  # the chosen point: after the first checkpoint, mid-run
    assert not (run / "fit.json").exists()
    p.send_signal(signal.SIGTERM)
    p.send_signal(signal.SIGCONT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    assert "Traceback" not in err
    assert f"morphgs fit: stopped by SIGTERM; a checkpoint is in {run}: rerun the same command to resume" in err
    assert not (run / "fit.json").exists()
    again = _run(*_fit(fit_data, run))
    assert again.returncode == 0, again.stderr
    assert _ply(run) == _ply(fit_data[2])
    assert _losses(run) == _losses(fit_data[2])


def test_a_damaged_fit_checkpoint_is_skipped_for_the_previous_one_and_none_left_is_one_line(
        fit_data: tuple[Path, Path, Path], tmp_path: Path) -> None:
    run = tmp_path / "run"
    p = _start(*_fit(fit_data, run))
    _until(lambda: (run / "checkpoint.prev.bin").is_file(), p)
    p.kill()  # SIGKILL after the second checkpoint
    p.communicate(timeout=60)
    ck = run / "checkpoint.bin"
    with open(ck, "r+b") as f:  # truncated in place: a crash during a copy, a full disk
        f.truncate(ck.stat().st_size // 2)
    again = _run(*_fit(fit_data, run))
    assert again.returncode == 0, again.stderr
    assert f"morphgs fit: warning: checkpoint {ck} is damaged (" in again.stderr
    assert _ply(run) == _ply(fit_data[2])
    assert _losses(run) == _losses(fit_data[2])
    # nothing verifies: one line saying so and how to start over
    (run / "fit.json").unlink()
    for name in ("checkpoint.bin", "checkpoint.prev.bin"):
        (run / name).unlink()
        (run / name).write_bytes(b"MGSFITCK" + b"\0" * 40)
    r = _run(*_fit(fit_data, run))
    line = one_error_line(r.returncode, r.stderr, "fit")
    assert f"{run}: no checkpoint verifies (checkpoint.bin, checkpoint.prev.bin damaged); rerun with --restart" in line


# ---- a full disk ----

def _limited(limit: int):  # type: ignore[no-untyped-def]
    def pre() -> None:  # in the child: writes past `limit` bytes fail with EFBIG instead of killing it
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


def test_a_full_disk_during_curate_is_one_line_naming_the_file_and_keeps_the_finished_pairs(
        tmp_path: Path, reference: Path) -> None:
    out = tmp_path / "ds"
    args = ["--size", "16x16", "--frames", "3", "-k", "3", "--sample-gaussians", "2000", "--no-progress"]
    r = _run("curate", "--out", str(out), *args, preexec_fn=_limited(2500))
    line = one_error_line(r.returncode, r.stderr, "curate")
    assert f"{out / 'manifest.jsonl'}: cannot append pair " in line and "File too large" in line
    kept = manifest.load(out)
    assert kept and all(manifest.is_complete(out, rec) for rec in kept.values())
    before = {k: (out / v["paths"]["cameras"]).read_bytes() for k, v in kept.items()}
    again = _run("curate", "--out", str(out), *args)
    assert again.returncode == 0, again.stderr
    assert "of 6 planned" in again.stderr and f"{len(kept)} already done" in again.stderr
    assert len(_lines(out / "manifest.jsonl")) == 6
    assert all((out / manifest.load(out)[k]["paths"]["cameras"]).read_bytes() == b for k, b in before.items())


def test_a_full_disk_during_fit_is_one_line(fit_data: tuple[Path, Path, Path], tmp_path: Path) -> None:
    run = tmp_path / "run"
    r = _run(*_fit(fit_data, run), preexec_fn=_limited(100_000))  # the checkpoint is ~1 MB
    line = one_error_line(r.returncode, r.stderr, "fit")
    assert f"{run / 'checkpoint.bin'}: File too large" in line
    assert not list(run.glob("*.tmp*")) and not (run / "checkpoint.bin").exists()  # no half-written checkpoint


# ---- the table: every subcommand, damaged inputs and unwritable outputs ----

@pytest.fixture(scope="module")
def damaged(tmp_path_factory: pytest.TempPathFactory, reference: Path) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("damaged")
    good = d / "good.ply"
    morphgs.save_ply(morphgs.synthetic.scene(300, seed=1), good)
    trunc = d / "truncated.ply"
    trunc.write_bytes(good.read_bytes()[: good.stat().st_size // 3])
    blocker = d / "a-file"
    blocker.write_text("not a folder\n")
    posed, _, _ = make_dataset(d / "posed", views=4, size=(16, 12), gaussians=300)
    (posed / "images" / "frame_00002.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 30)
    return {"good": good, "trunc": trunc, "blocker": blocker, "posed": posed, "data": reference,
            "missing": d / "missing"}


TABLE = [
    # (command, arguments, what the error line must name)
    ("info", ["{trunc}"], "{trunc}"),
    ("info", ["{missing}.ply"], "{missing}.ply"),
    ("convert", ["{trunc}", "{missing}.spz"], "{trunc}"),
    ("convert", ["{good}", "{blocker}/x.ply"], "{blocker}/x.ply"),
    ("perturb", ["{trunc}", "{missing}.ply", "--seed", "1"], "{trunc}"),
    ("sample", ["{blocker}/s.ply", "--gaussians", "100"], "{blocker}/s.ply"),
    ("curate", ["--out", "{blocker}/o", "--size", "16x16", "--frames", "2", "--no-progress"], "{blocker}/o"),
    ("fit", ["{missing}", "--out", "{missing}-run"], "{missing}"),
    ("fit", ["{posed}", "--out", "{missing}-fit", "--steps", "5", "--no-progress"], "frame_00002.png"),
    ("fit", ["{posed}", "--out", "{blocker}/run"], "{blocker}/run"),
    ("export", ["diffsynth", "{missing}", "{missing}-x"], "{missing}"),
    ("export", ["difix", "{data}", "{blocker}/x"], "{blocker}"),
    ("export-difix", ["{missing}", "{missing}.json"], "{missing}"),
    ("preview", ["{missing}"], "{missing}"),
]


@pytest.mark.parametrize("cmd,args,names", TABLE, ids=[f"{c}-{i}" for i, (c, _, _) in enumerate(TABLE)])
def test_every_failure_is_one_line_naming_the_file(cmd: str, args: list[str], names: str,
                                                   damaged: dict[str, Path]) -> None:
    fill = {k: str(v) for k, v in damaged.items()}
    r = _run(cmd, *[a.format(**fill) for a in args])
    line = one_error_line(r.returncode, r.stderr, cmd)
    assert names.format(**fill) in line


def test_signals_held_delivers_ctrl_c_and_sigterm_after_the_block_to_the_handlers_of_before() -> None:
    from morphgs.reliability import Preempted, sigterm_raises, signals_held

    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        done = []
        with pytest.raises(KeyboardInterrupt):
            with signals_held():
                signal.raise_signal(signal.SIGINT)
                done.append("rows written")  # the block ran to its end first
        assert done == ["rows written"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with sigterm_raises():
            with pytest.raises(Preempted):
                with signals_held():
                    signal.raise_signal(signal.SIGTERM)
                    done.append("again")
        assert done[-1] == "again"
        with signals_held():  # nothing arrived: nothing raised
            done.append("quiet")
    finally:
        signal.signal(signal.SIGINT, old)
