"""`morphgs ablate --preset smoke` end to end through the CLI, for real: every stage, the report,
and the cache's promises -- a second run recomputes nothing, two worker processes give the same
bytes, a SIGKILL during training loses no finished stage and the rerun's results equal an
uninterrupted run's, and changing one condition recomputes only what depends on it."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("accelerate")
pytest.importorskip("matplotlib")

ENV = {**os.environ, "MORPHGS_NUM_THREADS": "2"}


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "morphgs", "ablate", *args]


def _ablate(*args: str) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(_cmd(*args), env=ENV, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    return r


def _last_run(study: Path) -> dict:
    return json.loads((study / "runs.jsonl").read_text().splitlines()[-1])


@pytest.fixture(scope="module")
def smoke(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ablate") / "smoke"
    _ablate("--preset", "smoke", "--out", str(out))
    return out


def test_smoke_runs_every_stage_and_writes_the_report(smoke: Path) -> None:
    counts = _last_run(smoke)["counts"]
    # 3 scenes; 3 conditions (blur2d, morphological, target-S8) x 2 seeds, the target's sparse fit of
    # each of the 2 training scenes its own job; 1 test scene x 1 regime;
    # 6 trained rows + 3 control rows, each refined and scored in 2D and 3D
    assert counts == {"captures": {"computed": 3, "reused": 0}, "pairfits": {"computed": 2, "reused": 0},
                      "trainsets": {"computed": 3, "reused": 0},
                      "training": {"computed": 6, "reused": 0}, "testsets": {"computed": 1, "reused": 0},
                      "refine": {"computed": 9, "reused": 0}, "metrics2d": {"computed": 9, "reused": 0},
                      "metrics3d": {"computed": 9, "reused": 0}, "report": {"computed": 1, "reused": 0}}
    res = json.loads((smoke / "results.json").read_text())
    rows = {(r["condition"], r["seed"]) for r in res["records"]}
    assert rows == {(c, s) for c in ("blur2d", "morphological", "target-S8") for s in (0, 1)} | {
        ("input", None), ("identity", None), ("oracle", None)}
    for r in res["records"]:
        assert set(r) >= {"psnr2d", "ssim2d", "lpips2d", "eflow", "psnr3d", "ssim3d", "lpips3d", "chamfer",
                          "f@0.5%", "f@1%", "f@2%"}
        assert 0.0 <= r["f@1%"] <= 1.0 and r["f@0.5%"] <= r["f@1%"] <= r["f@2%"]
    oracle = next(r for r in res["records"] if r["condition"] == "oracle")
    inp = next(r for r in res["records"] if r["condition"] == "input")
    assert oracle["ssim2d"] == 1.0 and oracle["eflow"] == 0.0 and inp["ssim2d"] < 1.0
    assert oracle["psnr3d"] > inp["psnr3d"]  # a re-fit from the clean frames beats one from the sparse render
    # severity: the sparse target's training pairs are far more corrupted than the perturbations'
    sev = res["severity"]
    assert set(sev) == {"blur2d", "morphological", "target-S8"} and sev["target-S8"] < sev["morphological"]
    for c in res["cka"]:  # CKA against the initial model: 1 at step 0, probed every 5 of 20 steps
        assert c["steps"] == [0, 5, 10, 15, 20] and c["mean"][0] == pytest.approx(1.0) and c["mean"][-1] < 1.0
    table = (smoke / "table.md").read_text()
    assert "| S8 | target-S8 |" in table and "| S8 | (oracle) |" in table and "**" in table
    assert "each condition − target-S8" in table
    csv_lines = (smoke / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + len(res["records"]) and csv_lines[0].startswith("regime,condition,seed,scene,clip")
    for png in ("deltas.png", "cka.png", "qualitative.png"):
        assert (smoke / "plots" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_targets_sparse_fits_are_made_once_in_their_own_jobs_and_linked_into_its_training_set(
        smoke: Path) -> None:
    """Each training scene's sparse fit is a pairfits job; the target's training set links those
    fit folders (relative links, so a moved study keeps them) and its pairs come from them: curate
    found them made and fitted nothing itself."""
    from morphgs.curation import manifest

    (ts,) = (smoke / "trainsets").glob("target-S8-*")
    fits = sorted((ts / "data" / "fits").iterdir())
    assert len(fits) == 2
    for f in fits:
        assert f.is_symlink() and not os.path.isabs(os.readlink(f))
        assert f.resolve().parent.parent.parent.parent == (smoke / "pairfits").resolve()
        (run,) = f.glob("*/run")
        assert (run / "fit.json").is_file()
    recs = manifest.load(ts / "data").values()
    assert {r["fit"]["dir"].split("/")[1] for r in recs} == {f.name for f in fits}
    assert len(list((smoke / "pairfits").iterdir())) == 2


def test_a_second_run_recomputes_nothing(smoke: Path) -> None:
    before = (smoke / "results.json").read_bytes()
    r = _ablate("--preset", "smoke", "--out", str(smoke))
    assert "0 stage output(s) computed, 43 reused" in r.stderr
    assert all(c["computed"] == 0 for c in _last_run(smoke)["counts"].values())
    assert (smoke / "results.json").read_bytes() == before


def _assert_cpu_logged(rec: dict) -> None:
    """A runs.jsonl record has the CPU seconds of every computed job (none for a reused one) and
    per stage, for the same stages as the wall seconds, above zero for each stage that computed
    and equal to its jobs' sum. Only that they are there and add up: no time is checked."""
    for j in rec["jobs"]:
        assert ("cpu_seconds" in j) == (j["status"] == "computed"), j
        assert j.get("cpu_seconds", 0.0) >= 0.0, j
    assert set(rec["stage_cpu_seconds"]) == set(rec["stage_seconds"])
    for stage, cpu in rec["stage_cpu_seconds"].items():
        assert cpu > 0.0, stage
        jobs = [j["cpu_seconds"] for j in rec["jobs"] if j["stage"] == stage and j["status"] == "computed"]
        assert cpu == pytest.approx(sum(jobs), abs=0.01), stage


def test_runs_jsonl_has_every_computed_jobs_cpu_seconds_and_each_stages(smoke: Path) -> None:
    records = [json.loads(x) for x in (smoke / "runs.jsonl").read_text().splitlines()]
    first = records[0]  # the fixture's run, in this process (a rerun's record computes nothing)
    assert sum(c["computed"] for c in first["counts"].values()) == 43
    assert set(first["stage_cpu_seconds"]) == {"captures", "trainsets", "pairfits", "training", "testsets",
                                               "refine", "metrics2d", "metrics3d", "report"}
    for rec in records:
        _assert_cpu_logged(rec)


def test_two_workers_give_the_same_bytes(smoke: Path, tmp_path: Path) -> None:
    out = tmp_path / "j2"
    _ablate("--preset", "smoke", "--out", str(out), "-j", "2")
    for f in ("results.json", "results.csv", "table.md"):
        assert (out / f).read_bytes() == (smoke / f).read_bytes(), f
    _assert_cpu_logged(_last_run(out))  # measured in the worker processes


def test_the_ray_backend_gives_the_same_bytes(smoke: Path, tmp_path: Path) -> None:
    # CI installs the ray extra, so there a missing Ray is a failure, not a skip
    __import__("ray") if os.environ.get("CI") else pytest.importorskip("ray")
    out = tmp_path / "ray"
    _ablate("--preset", "smoke", "--out", str(out), "--backend", "ray", "-j", "2")
    for f in ("results.json", "results.csv", "table.md"):
        assert (out / f).read_bytes() == (smoke / f).read_bytes(), f
    _assert_cpu_logged(_last_run(out))  # measured in the Ray workers


def _wait_for_a_training_checkpoint(proc: subprocess.Popen, out: Path) -> None:
    """Until a refiner training of the study at `out` has written a checkpoint (or the process
    ended, or 10 minutes passed)."""
    deadline = time.monotonic() + 600
    while proc.poll() is None and time.monotonic() < deadline:
        if any((out / "training").glob(".*.work/run/checkpoints/step-*")):
            return
        time.sleep(0.005)


def test_sigkill_during_training_then_rerun_gives_the_uninterrupted_results(smoke: Path, tmp_path: Path) -> None:
    out = tmp_path / "killed"
    proc = subprocess.Popen(_cmd("--preset", "smoke", "--out", str(out)), env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        _wait_for_a_training_checkpoint(proc, out)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL  # killed mid-study, not finished
    assert not (out / "table.md").exists()
    partial = list((out / "training").glob(".*.work"))
    assert partial  # a training run was in progress
    finished_before = {p.name for st in ("captures", "trainsets", "training") for p in (out / st).iterdir()
                       if (p / "stage.json").is_file()}
    assert any(n.startswith("blur2d-") for n in finished_before)  # the training sets were done
    _ablate("--preset", "smoke", "--out", str(out))
    reused = {e["name"] for e in _last_run(out)["jobs"] if e["status"] == "reused"}
    assert {n.rsplit("-", 1)[0] for n in finished_before} <= reused  # no finished stage was lost
    resumed = [json.loads(p.read_text()) for p in (out / "training").glob("*/train.json")]
    assert any(t["resumed"] for t in resumed)  # the killed run continued from its checkpoint
    for f in ("results.json", "results.csv", "table.md"):
        assert (out / f).read_bytes() == (smoke / f).read_bytes(), f


def _children(pid: int) -> list[int]:
    """Live processes whose parent is `pid` (from /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[1]) == pid and fields[0] != "Z":
                out.append(int(d.name))
    return out


@pytest.mark.parametrize("workers", ["1", "2"])
def test_sigterm_during_training_stops_the_study_without_finishing_the_training(
        workers: str, smoke: Path, tmp_path: Path) -> None:
    """SIGTERM sent to the `morphgs ablate` process alone (as Kubernetes or `kill PID` do, not to
    its process group) while refiners train: the training loop checkpoints and returns early, and
    the study stops there. The half-trained runs are not taken for finished stages (before the fix
    they were, and a rerun reused them), `-j 2` does not wait for its workers' trainings (it
    stops them), and the rerun continues from the checkpoints to the uninterrupted results."""
    out = tmp_path / "stopped"
    proc = subprocess.Popen(_cmd("--preset", "smoke", "--out", str(out), "-j", workers), env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _wait_for_a_training_checkpoint(proc, out)
        children = [c for c in _children(proc.pid) if "spawn_main" in Path(f"/proc/{c}/cmdline").read_text()]
        assert children or workers == "1", "no worker process was running a job"
        in_flight = [p.name[1:-len(".work")] for p in (out / "training").glob(".*.work")]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)  # a hang guard: before the fix it waited for the trainings
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 143, err[-2000:]
    assert "morphgs ablate: stopped by SIGTERM; finished stages are kept; rerun the same command to continue" in err
    assert "Traceback" not in err
    assert not (out / "table.md").exists()
    alive = [w for w in children if Path(f"/proc/{w}").exists()
             and Path(f"/proc/{w}/stat").read_text().split(")")[-1].split()[0] != "Z"]
    assert not alive, f"worker processes {alive} outlived the stop"
    # the trainings in flight were stopped, not waited for (a race may let one finish at the signal)
    assert any(not (out / "training" / n / "stage.json").is_file() for n in in_flight), in_flight
    _ablate("--preset", "smoke", "--out", str(out), "-j", workers)
    resumed = [json.loads(p.read_text()) for p in (out / "training").glob("*/train.json")]
    assert any(t["resumed"] for t in resumed)  # a stopped run continued from its checkpoint
    for f in ("results.json", "results.csv", "table.md"):
        assert (out / f).read_bytes() == (smoke / f).read_bytes(), f


def test_changing_one_condition_recomputes_only_that_condition(smoke: Path, tmp_path: Path) -> None:
    out = tmp_path / "changed"
    shutil.copytree(smoke, out, symlinks=True)
    study = tmp_path / "study.toml"
    study.write_text('preset = "smoke"\n[conditions]\ntrain = ["blur2d", "spatial"]\n', encoding="utf-8")
    r = subprocess.run(_cmd("--study", str(study), "--out", str(out)), env=ENV, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 1
    assert r.stderr.count("\n") == 1 and "other settings (conditions.train: " in r.stderr and "--recompute" in r.stderr
    _ablate("--study", str(study), "--out", str(out), "--recompute")
    computed = sorted((e["stage"], e["name"]) for e in _last_run(out)["jobs"] if e["status"] == "computed")
    rows = [f"spatial-s{s}-sample-2-S8" for s in (0, 1)]
    assert computed == sorted([("trainsets", "spatial"), ("training", "spatial-s0"), ("training", "spatial-s1"),
                               *[(st, r) for st in ("refine", "metrics2d", "metrics3d") for r in rows],
                               ("report", "report")])
    res = json.loads((out / "results.json").read_text())
    assert {r["condition"] for r in res["records"]} == {"blur2d", "spatial", "target-S8", "input", "identity",
                                                        "oracle"}
    old = json.loads((smoke / "results.json").read_text())
    keep = [r for r in old["records"] if r["condition"] != "morphological"]
    assert [r for r in res["records"] if r["condition"] != "spatial"] == keep  # unchanged rows: the same values


def test_bumping_a_stage_version_remakes_it_and_what_reads_it_nothing_else(
        smoke: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from morphgs.ablation import load_study, run_study
    from morphgs.ablation.stages import metrics2d

    out = tmp_path / "bumped"
    shutil.copytree(smoke, out, symlinks=True)
    monkeypatch.setattr(metrics2d, "VERSION", metrics2d.VERSION + 1)
    monkeypatch.setenv("MORPHGS_NUM_THREADS", "2")
    ledger = run_study(load_study(None, preset="smoke"), out, log=lambda m: None)
    computed = sorted({e["stage"] for e in ledger.entries if e["status"] == "computed"})
    assert computed == ["metrics2d", "report"] and ledger.counts()["metrics2d"] == {"computed": 9, "reused": 0}
    assert (out / "results.json").read_bytes() == (smoke / "results.json").read_bytes()  # the same code: same bytes


def test_the_2d_metrics_stage_alone_reads_lpips_as_na_with_its_reason(smoke: Path, tmp_path: Path) -> None:
    from morphgs.ablation.stages import metrics2d

    refined = next((smoke / "refine").glob("morphological-s0-*"))
    testset = next((smoke / "testsets").glob("sample-2-S8-*"))
    note = metrics2d.lpips_status("off", "alex")
    metrics2d.make(tmp_path, testset_dir=str(testset), refined_dir=str(refined), lpips_note=note, lpips_net="alex",
                   eflow=False, threads=1)
    out = json.loads((tmp_path / "metrics2d.json").read_text())
    assert out["lpips_note"] == 'LPIPS turned off in the study ([metrics] lpips = "off")'
    (row,) = out["clips"].values()
    assert row["lpips2d"] is None and row["eflow"] is None
    whole = next(r for r in json.loads((smoke / "results.json").read_text())["records"]
                 if r["condition"] == "morphological" and r["seed"] == 0)
    assert row["psnr2d"] == whole["psnr2d"] and row["ssim2d"] == whole["ssim2d"]  # the same functions, the same bits


def test_a_damaged_stage_output_is_named_and_made_again(smoke: Path, tmp_path: Path) -> None:
    out = tmp_path / "damaged"
    shutil.copytree(smoke, out, symlinks=True)
    metrics = next((out / "metrics2d").glob("morphological-s0-*"))
    victim = metrics / "metrics2d.json"
    victim.write_bytes(victim.read_bytes()[:10])  # truncated, as by a full disk or a bad sync
    r = _ablate("--preset", "smoke", "--out", str(out))
    assert f"morphgs ablate: warning: {metrics}: damaged stage output" in r.stderr
    computed = sorted((e["stage"], e["name"]) for e in _last_run(out)["jobs"] if e["status"] == "computed")
    assert computed == [("metrics2d", metrics.name.rsplit("-", 1)[0])]  # only the damaged output is remade
    assert (metrics.parent / f"{metrics.name}.damaged").is_dir()
    for f in ("results.json", "results.csv", "table.md"):
        assert (out / f).read_bytes() == (smoke / f).read_bytes(), f


def test_a_second_ablate_into_a_study_being_written_is_refused(smoke: Path, tmp_path: Path) -> None:
    from morphgs.reliability import folder_lock

    out = tmp_path / "busy"
    shutil.copytree(smoke, out, symlinks=True)
    with folder_lock(out, command="ablate"):  # this test process is the other writer
        r = subprocess.run(_cmd("--preset", "smoke", "--out", str(out)), env=ENV, capture_output=True, text=True,
                           timeout=600)
    assert r.returncode == 1 and r.stderr.count("\n") == 1
    assert r.stderr.startswith("morphgs ablate: error: ") and f"pid {os.getpid()}" in r.stderr
    assert "--wait" in r.stderr
