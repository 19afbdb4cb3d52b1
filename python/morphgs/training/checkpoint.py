"""Checkpoints of a run: `RUN/checkpoints/step-NNNNNNN/`, written atomically.

A checkpoint is accelerate's `save_state` folder (optimizer, the LR scheduler, every process's
random states, the loop's `TrainState`) plus the model's `save_trained` output
(`trained.safetensors` for the built-in models; accelerate's own copy of the weights is skipped)
and `state.json` (step, wall time). It is written under `.tmp-step-NNNNNNN` and renamed into place
once complete, so a killed run leaves either a whole checkpoint or a temporary the next run
removes. The last `keep` checkpoints are kept.

`checksums.json` (size and sha256 of every file, morphgs.reliability) is written last, before the
rename. `--resume` takes the highest step that verifies against it and loads; each damaged one
(truncated by a crash during a copy, a full disk, a bad sync) is skipped with a warning.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsError
from morphgs.reliability import one_line, verify_checksums, write_checksums

__all__ = ["CheckpointWriteError", "TrainState", "checkpoint_dir", "latest_checkpoint", "list_checkpoints", "save_checkpoint",
           "verify_checkpoint"]

CHECKPOINTS = "checkpoints"
STATE_FILE = "state.json"


class CheckpointWriteError(MorphgsError):
    """A checkpoint that could not be written (a full disk, an unwritable run folder)."""


class TrainState:
    """The loop's position, checkpointed with the run: optimizer steps done. The data position
    (micro-batches consumed per process) and every seed derive from it."""

    def __init__(self, step: int = 0) -> None:
        self.step = step

    def state_dict(self) -> dict[str, Any]:
        return {"step": self.step}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = int(state["step"])


def checkpoint_dir(run_dir: str | os.PathLike[str], step: int) -> Path:
    """The folder of the checkpoint after `step` optimizer steps."""
    return Path(run_dir) / CHECKPOINTS / f"step-{step:07d}"


def list_checkpoints(run_dir: str | os.PathLike[str]) -> list[tuple[int, Path]]:
    """Complete checkpoints of a run as (step, folder), oldest first."""
    root = Path(run_dir) / CHECKPOINTS
    out = []
    if root.is_dir():
        for d in root.iterdir():
            if d.name.startswith("step-") and (d / STATE_FILE).is_file():
                try:
                    out.append((int(d.name[5:]), d))
                except ValueError:
                    continue
    return sorted(out)


def latest_checkpoint(run_dir: str | os.PathLike[str]) -> Path | None:
    """The highest complete checkpoint, or None."""
    found = list_checkpoints(run_dir)
    return found[-1][1] if found else None


def verify_checkpoint(folder: str | os.PathLike[str]) -> str | None:
    """None when a checkpoint's files match the checksums written with them, else what is wrong
    (naming the file). Checkpoints from before checksums existed pass."""
    return verify_checksums(folder)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save_checkpoint(accelerator: Any, run_dir: str | os.PathLike[str], step: int, *, keep: int,
                    info: dict[str, Any] | None = None) -> Path:
    """Write the checkpoint of `step` atomically (every process calls this) and prune old ones.

    Returns:
        The checkpoint folder.
    """
    final = checkpoint_dir(run_dir, step)
    tmp = final.with_name(f".tmp-{final.name}")
    if final.exists():
        return final
    try:
        _write(accelerator, tmp, step, info)
    except Exception as e:  # a full disk: no half-written checkpoint, the earlier ones kept
        shutil.rmtree(tmp, ignore_errors=True)
        raise CheckpointWriteError(f"{final}: cannot write the checkpoint ({one_line(e)}); the earlier checkpoints "
                                   "are kept: free some space, then rerun with --resume") from None
    if accelerator.is_main_process:
        os.replace(tmp, final)
        _fsync_dir(final.parent)
        for _, old in list_checkpoints(run_dir)[:-keep]:
            shutil.rmtree(old, ignore_errors=True)
    accelerator.wait_for_everyone()
    return final


def _write(accelerator: Any, tmp: Path, step: int, info: dict[str, Any] | None) -> None:
    """Every file of a checkpoint into `tmp`, checksums last, all fsynced."""
    if accelerator.is_main_process:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    accelerator.wait_for_everyone()
    accelerator.save_state(str(tmp))
    accelerator.wait_for_everyone()
    if accelerator.is_main_process:
        state = {"step": step, "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S"), **(info or {})}
        (tmp / STATE_FILE).write_text(json.dumps(state, indent=1) + "\n", encoding="utf-8")
        for f in tmp.rglob("*"):
            if f.is_file():
                with open(f, "rb") as fh:
                    os.fsync(fh.fileno())
        write_checksums(tmp)


def remove_stale_temporaries(run_dir: str | os.PathLike[str]) -> None:
    """Delete checkpoint temporaries a killed run left behind."""
    root = Path(run_dir) / CHECKPOINTS
    if root.is_dir():
        for d in root.glob(".tmp-step-*"):
            shutil.rmtree(d, ignore_errors=True)
