"""Reliability of `morphgs train` (and the commands beside it that need torch) through the real CLI
(docs/reliability.md): damaged checkpoints skipped for the newest one that verifies, an
unreadable frame as one line (the DataLoader worker's traceback unwrapped) or skipped with
`data.skip_bad`, SIGTERM stopping with a checkpoint and a resume giving the same losses and
bytes, a full disk, and a damaged latent cache encoded again."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("accelerate")

from safetensors.torch import load_file  # noqa: E402

from test_reliability import _limited, _run, _start, _until, one_error_line  # noqa: E402
from train_helpers import curated, small_overrides  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 train pairs (sample-1) and 3 test pairs (sample-0) of 8 frames, 48x40."""
    return curated(tmp_path_factory.mktemp("reltrain") / "ds", pairs_per_scene=3, frames=8, resolution=(48, 40))


def _sets(sections: dict[str, dict[str, object]]) -> list[str]:
    # whole 8-frame clips: every window reads every frame of its pair
    over = small_overrides(**{**sections, "data": {"frames": 8, **sections.get("data", {})}})
    return [a for sec, values in over.items() for k, v in values.items()
            for a in ("--set", f"{sec}.{k}={json.dumps(v)}")]


def _train(dataset: Path, out: Path, sections: dict[str, dict[str, object]] | None = None) -> list[str]:
    return ["train", "--no-progress", "--data", str(dataset), "--out", str(out), *_sets(sections or {})]


def _losses(run: Path) -> list[tuple[str, str]]:
    import csv

    with open(run / "logs" / "train.csv", encoding="utf-8") as f:
        return [(r["step"], r["loss"]) for r in csv.DictReader(f)]


def _weights(ckpt: Path) -> dict[str, bytes]:
    return {k: v.numpy().tobytes() for k, v in load_file(str(ckpt / "trained.safetensors")).items()}


def _damage(path: Path) -> None:
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size // 2)


def _a_train_frame(data: Path) -> Path:
    recs = [json.loads(ln) for ln in (data / "manifest.jsonl").read_text().splitlines()]
    rec = sorted((r for r in recs if r["split"] == "train"), key=lambda r: r["pair_id"])[1]
    return data / rec["paths"]["corrupted"] / "00003.png"


@pytest.fixture()
def bad_frame(data: Path) -> tuple[Path, str]:
    """One unreadable frame in a train pair (restored afterwards)."""
    frame = _a_train_frame(data)
    good = frame.read_bytes()
    frame.write_bytes(good[:40])  # a PNG cut short
    pair = frame.parent.parent.relative_to(data / "pairs").as_posix()
    yield frame, pair
    frame.write_bytes(good)


def test_resume_skips_damaged_checkpoints_for_the_newest_that_verifies(data: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    sections = dict(optim={"max_steps": 6}, run={"checkpoint_every": 2, "keep_checkpoints": 3})
    r = _run(*_train(data, run, sections))
    assert r.returncode == 0, r.stderr
    ck = run / "checkpoints"
    want, losses = _weights(ck / "step-0000006"), _losses(run)
    _damage(ck / "step-0000006" / "optimizer.bin")  # found by loading it (as a checkpoint without checksums)
    (ck / "step-0000006" / "checksums.json").unlink()
    _damage(ck / "step-0000004" / "trained.safetensors")  # found by its checksum
    again = _run("train", "--no-progress", "--out", str(run), "--resume")
    assert again.returncode == 0, again.stderr
    for step in ("step-0000006", "step-0000004"):
        assert f"morphgs train: warning: checkpoint {ck / step} is damaged (" in again.stderr
    assert "step-0000006 is damaged (cannot be loaded (" in again.stderr
    assert f"step-0000004 is damaged ({ck / 'step-0000004' / 'trained.safetensors'} has " in again.stderr
    assert f"resumed {run} at step 2 (step-0000002)" in again.stderr
    assert _weights(ck / "step-0000006") == want  # the same bytes as the run never damaged
    assert _losses(run) == losses
    # none verifies: one line saying so and how to start over
    for step in ("step-0000002", "step-0000004", "step-0000006"):
        _damage(ck / step / "trained.safetensors")
    r = _run("train", "--no-progress", "--out", str(run), "--resume")
    line = one_error_line(r.returncode, r.stderr, "train")
    assert f"{run}: no checkpoint verifies (step-0000006, step-0000004, step-0000002 damaged)" in line
    assert "Traceback" not in r.stderr and "PytorchStreamReader" not in line
    assert "start over without --resume" in line


def test_an_unreadable_frame_is_one_line_naming_it_not_a_worker_traceback(data: Path, tmp_path: Path,
                                                                           bad_frame: tuple[Path, str]) -> None:
    frame, _ = bad_frame
    r = _run(*_train(data, tmp_path / "run", {"data": {"num_workers": 1}}))
    line = one_error_line(r.returncode, r.stderr, "train")
    assert str(frame) in line


def test_skip_bad_skips_logs_and_counts_the_pair_and_stops_past_the_share(data: Path, tmp_path: Path,
                                                                       bad_frame: tuple[Path, str]) -> None:
    frame, pair = bad_frame
    run = tmp_path / "run"
    r = _run(*_train(data, run, {"data": {"num_workers": 1, "skip_bad": True, "max_bad_share": 0.5}}))
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert f"morphgs train: warning: skipping pair {pair}: " in r.stderr
    assert f"skipped 1 unreadable pair(s) of 3 (data.skip_bad); listed in {run / 'bad_pairs.jsonl'}" in r.stderr
    assert f"{run}: 10 steps, " in r.stdout and ", 1 unreadable pair(s) skipped (bad_pairs.jsonl)" in r.stdout
    logged = [json.loads(ln) for ln in (run / "bad_pairs.jsonl").read_text().splitlines()]
    assert [e["pair_id"] for e in logged] == [pair] and str(frame) in logged[0]["error"]
    # more bad pairs than the share allows: one line, stop
    r = _run(*_train(data, tmp_path / "run2", {"data": {"num_workers": 0, "skip_bad": True, "max_bad_share": 0.2}}))
    line = one_error_line(r.returncode, r.stderr, "train")
    assert "1 of 3 pairs cannot be read (more than data.max_bad_share = 0.2)" in line


def test_sigterm_checkpoints_and_the_resumed_run_gives_the_same_losses_and_bytes(data: Path, tmp_path: Path) -> None:
    sections = dict(data={"num_workers": 1}, optim={"max_steps": 16},
                    run={"checkpoint_every": 4, "keep_checkpoints": 5})
    whole = _run(*_train(data, tmp_path / "whole", sections))
    assert whole.returncode == 0, whole.stderr
    run = tmp_path / "run"
    p = _start(*_train(data, run, sections), start_new_session=True)
    _until(lambda: (run / "checkpoints" / "step-0000004").is_dir(), p)
    # the chosen point: after the first checkpoint; to the whole process group (the DataLoader
    # worker too), as a cluster sends it
    os.killpg(p.pid, signal.SIGSTOP)
    os.killpg(p.pid, signal.SIGTERM)
    os.killpg(p.pid, signal.SIGCONT)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 143, err
    assert "Traceback" not in err
    stopped = [ln for ln in err.splitlines() if ln.startswith("morphgs train: stopped by SIGTERM at step ")]
    assert len(stopped) == 1 and f"rerun with --out {run} --resume to continue" in stopped[0]
    step = int(stopped[0].split("at step ")[1].split()[0])
    assert 4 <= step < 16 and (run / "checkpoints" / f"step-{step:07d}").is_dir()
    again = _run("train", "--no-progress", "--out", str(run), "--resume")
    assert again.returncode == 0, again.stderr
    assert f"resumed {run} at step {step}" in again.stderr
    assert _losses(run) == _losses(tmp_path / "whole")
    assert _weights(run / "checkpoints" / "step-0000016") == _weights(tmp_path / "whole" / "checkpoints" / "step-0000016")


def test_a_full_disk_during_train_is_one_line_and_leaves_no_half_checkpoint(data: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    r = _run(*_train(data, run), preexec_fn=_limited(20_000))  # the first checkpoint is larger
    line = one_error_line(r.returncode, r.stderr, "train")
    assert f"{run / 'checkpoints' / 'step-0000005'}: cannot write the checkpoint (" in line
    assert "File too large" in line
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == []


@pytest.fixture(scope="module")
def missing(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("missing") / "nothing-here"


@pytest.mark.parametrize("cmd,args", [
    ("train", ["--data", "{m}", "--out", "{m}-run"]),
    ("train", ["--out", "{m}", "--resume"]),
    ("refine", ["{m}", "{m}.mp4", "--out", "{m}-out"]),
    ("eval", ["{m}", "{m}-gt", "--out", "{m}-eval"]),
])
def test_torch_commands_fail_in_one_line_naming_the_missing_path(cmd: str, args: list[str], missing: Path) -> None:
    r = _run(cmd, *[a.format(m=missing) for a in args])
    assert str(missing) in one_error_line(r.returncode, r.stderr, cmd)


def test_a_truncated_latent_cache_is_encoded_again_with_a_warning(tmp_path: Path) -> None:
    pytest.importorskip("diffusers")
    import torch
    from diffusers import AutoencoderKL

    from morphgs import MorphgsWarning
    from morphgs.diffusion import tiny as td
    from morphgs.diffusion.codecs import SDCodec
    from morphgs.diffusion.latent_cache import CacheKey, CacheSource, build_cache

    codec = SDCodec(AutoencoderKL.from_pretrained(td.sd15_folder(tmp_path / "sd15") / "vae", local_files_only=True))
    key = CacheKey(model="sandbox", vae="v", text_encoder="t", height=32, width=32, frames=3, stride=3,
                   dtype="float32", dataset="d", split="train", prompts="p", text_tokens=16)
    g = torch.Generator().manual_seed(0)
    sources = [CacheSource(pair_id=f"p{i}", start=0, clean=torch.rand(3, 3, 32, 32, generator=g) * 2 - 1,
                           corrupted=torch.rand(3, 3, 32, 32, generator=g) * 2 - 1, prompt="x") for i in range(2)]
    text = lambda prompts: torch.ones(len(prompts), 4, 8)  # noqa: E731
    root = tmp_path / "cache"
    build_cache(root, key, sources, posterior=codec.posterior, encode_text=text)
    item = root / "items" / "000001.safetensors"
    want = item.read_bytes()
    _damage(item)
    with pytest.warns(MorphgsWarning, match=f"latent cache {root} is damaged \\({item} has "):
        cache = build_cache(root, key, sources, posterior=codec.posterior, encode_text=text)
    assert item.read_bytes() == want and len(cache) == 2
