"""`train(...)` — the training loop of `morphgs train`, one readable recipe from top to bottom.

HF accelerate does device placement, bf16 autocast, DDP and gradient accumulation; the loop
knows nothing about the model beyond the `Refiner` protocol (morphgs.models.base). Layout of a
run folder, checkpoint contents and the resume guarantee: docs/training.md.

Determinism: the data stream is a pure function of (seed, micro-batches consumed), the objective's
generator is seeded from (seed, step, micro-batch, rank), and a checkpoint restores model,
optimizer, scheduler, step and every process's random states, so `resume=True` after a kill
continues with the same losses as the run that was never interrupted.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from morphgs._core import MorphgsError, MorphgsWarning
from morphgs.configfile import ConfigError
from morphgs.data import DatasetError, LivePairs, PairDataset, load_records, sample_seed, train_loader
from morphgs.data.skip import SkipBadPairs, bad_entries
from morphgs.models.base import ModelContext, Refiner
from morphgs.models.registry import create_model
from morphgs.reliability import StopRequest, folder_lock, is_lock_file, unwrap_worker_message
from morphgs.training.checkpoint import (TrainState, latest_checkpoint, list_checkpoints, remove_stale_temporaries,
                                         save_checkpoint, verify_checkpoint)
from morphgs.training.config import ResolvedConfig, TrainConfig, resolve_config
from morphgs.training.logs import Logs, preview_strip
from morphgs.training.schedule import make_scheduler

__all__ = ["TrainResult", "TrainingError", "train"]

RUN_FILE = "run.json"
BAD_PAIRS = "bad_pairs.jsonl"
_OBJECTIVE_SALT = 0x0B1EC7


class TrainingError(MorphgsError):
    """A run that cannot start or go on (names the run folder and the problem)."""


@dataclass
class TrainResult:
    """What a finished (or time-limited) run did."""

    run_dir: Path
    steps: int
    checkpoint: Path
    losses: list[tuple[int, float]] = field(default_factory=list)
    validation: dict[str, float] = field(default_factory=dict)
    stopped_early: bool = False
    seconds: float = 0.0
    preempted: str | None = None
    bad_pairs: int = 0


def train(
    data: str | os.PathLike[str] | None,
    *,
    out: str | os.PathLike[str],
    model: str | None = None,
    config: str | os.PathLike[str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    resume: bool = False,
    scenes: Sequence[str | os.PathLike[str]] = (),
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    wait: bool = False,
) -> TrainResult:
    """Train a refiner on a curated folder (or on live pairs) into a run folder.

    Args:
        data: the curated folder (`morphgs curate` output): its train split trains, its test split
            validates. May be None with live pairs (then no validation).
        out: the run folder (created; with `resume`, an existing run).
        model: a registered model name (default: the config's, else "tiny").
        config: a run config TOML (keys it leaves out come from the model's shipped config).
        overrides: nested {section: {key: value}} applied last (what --set and the flags give).
        resume: continue the run in `out` from its latest checkpoint, with its own config.
        scenes: scene files/folders for live pairs (`[data] live = true`; none: built-in scenes).
        progress: show a progress bar (main process).
        log: where messages go (default: print to stderr on the main process).
        wait: when another process writes `out`, wait for it instead of raising FolderBusyError.

    SIGTERM and a first Ctrl-C stop the run after the current step with a checkpoint
    (`TrainResult.preempted` names the signal); `resume=True` then continues it with the same
    losses as a run never interrupted.

    Returns:
        TrainResult.

    Raises:
        FileNotFoundError, DatasetError, ConfigError, TrainingError: bad data, config or run folder
        (each names the path and the problem). morphgs.reliability.FolderBusyError: another
        process writes `out`.
    """
    from accelerate import Accelerator

    run_dir = Path(out)
    resolved = _resolve(run_dir, model, config, overrides, resume, data)
    cfg = resolved.config
    data_dir = Path(data) if data is not None else _saved_data(run_dir) if resume else None
    accelerator = Accelerator(mixed_precision=_precision(cfg), gradient_accumulation_steps=cfg.optim.grad_accum,
                              cpu=_use_cpu(cfg), step_scheduler_with_optimizer=False)
    lock = folder_lock(run_dir, command="train", wait=wait) if accelerator.is_main_process else nullcontext()
    try:
        with lock:
            return _run(accelerator, resolved, run_dir, data_dir, scenes, resume, progress, log)
    finally:
        _release(accelerator)


def _run(accelerator: Any, resolved: ResolvedConfig, run_dir: Path, data_dir: Path | None, scenes: Sequence[Any],
         resume: bool, progress: bool, log: Callable[[str], None] | None) -> TrainResult:
    """The recipe, once accelerate is set up."""
    from accelerate.utils import set_seed

    cfg = resolved.config
    main = accelerator.is_main_process
    say = log or ((lambda m: print(m, file=sys.stderr, flush=True)) if main else (lambda m: None))
    rank, world, device = accelerator.process_index, accelerator.num_processes, accelerator.device
    if cfg.run.threads:
        torch.set_num_threads(cfg.run.threads)

    # ---- data, then the run folder (every process checks, then the main one writes) ----
    _check_run_dir(run_dir, resume)
    train_ds, val_pairs = _datasets(cfg, data_dir, scenes, say)
    val_ds: PairDataset | SkipBadPairs | None = val_pairs
    if cfg.data.skip_bad and isinstance(train_ds, PairDataset):
        train_ds = SkipBadPairs(train_ds)
        val_ds = SkipBadPairs(val_pairs) if val_pairs is not None else None
    accelerator.wait_for_everyone()
    if main and not resume:
        _start_run_dir(run_dir, resolved, data_dir, scenes, accelerator)
    accelerator.wait_for_everyone()

    # ---- the model ----
    ctx = ModelContext(frames=cfg.data.frames, size=cfg.data.size, reference=cfg.data.reference, training=True,
                       run_dir=run_dir, cache_dir=run_dir / "cache")
    torch.manual_seed(cfg.seed)  # the same initial weights on every process
    refiner = create_model(cfg.model, cfg.model_config, ctx)
    n_pairs = len(train_ds)
    train_ds = refiner.prepare_data(train_ds, ctx=ctx, accelerator=accelerator)
    set_seed(cfg.seed, device_specific=True)  # then each process its own random stream (dropout)

    o = cfg.optim
    optimizer = _adamw(refiner.param_groups(lr=o.lr, weight_decay=o.weight_decay), o, say)
    scheduler = make_scheduler(optimizer, warmup=o.warmup, total_steps=o.max_steps, schedule=o.schedule)
    model_p, optimizer_p = accelerator.prepare(refiner, optimizer)
    state = TrainState()
    accelerator.register_for_checkpointing(scheduler)
    accelerator.register_for_checkpointing(state)
    _checkpoint_hooks(accelerator)
    params = [p for p in model_p.parameters() if p.requires_grad]

    logs = Logs(run_dir, enabled=main)
    if resume:
        if main:
            remove_stale_temporaries(run_dir)
        ckpt = _load_newest_good(accelerator, run_dir)
        logs.resume_at(state.step)
        say(f"resumed {run_dir} at step {state.step} ({ckpt.name})")
    else:
        say(f"training {cfg.model} ({sum(p.numel() for p in params):,} trainable parameters) into {run_dir}: "
            f"{o.max_steps} steps, {world} process(es) on {device}, precision {accelerator.mixed_precision}")

    loader = train_loader(train_ds, batch_size=cfg.data.batch_size, num_workers=cfg.data.num_workers,
                          seed=cfg.seed, rank=rank, world_size=world, start_batch=state.step * o.grad_accum)
    batches = iter(loader)
    unwrapped = accelerator.unwrap_model(model_p)

    bar = _progress(progress and main, o.max_steps, state.step)
    t0 = time.perf_counter()
    start_step = state.step
    result = TrainResult(run_dir, state.step, run_dir)
    grad_norm = torch.zeros((), device=device)
    bad = _BadPairs(run_dir, n_pairs, cfg.data.max_bad_share, enabled=main, say=say)
    stop_request = StopRequest()
    try:
        stop_request.__enter__()
        while state.step < o.max_steps:
            model_p.train()
            sums: dict[str, torch.Tensor] = {}
            for micro in range(o.grad_accum):
                batch = _to_device(_next_batch(batches), device)
                if "bad" in batch:
                    bad.add(state.step + 1, bad_entries(batch.pop("bad")))
                gen = torch.Generator(device=device)
                gen.manual_seed(sample_seed(cfg.seed ^ _OBJECTIVE_SALT, state.step, micro * world + rank))
                with accelerator.accumulate(model_p):
                    loss, step_logs = model_p(batch, generator=gen)
                    if not torch.isfinite(loss.detach()):
                        raise TrainingError(f"{run_dir}: the loss is {loss.detach().item()} at step {state.step + 1} "
                                            f"(lr {scheduler.get_last_lr()[0]:.3g}); lower [optim] lr")
                    accelerator.backward(loss)
                    if accelerator.sync_gradients and o.grad_clip > 0:
                        grad_norm = accelerator.clip_grad_norm_(params, o.grad_clip)
                    optimizer_p.step()
                    optimizer_p.zero_grad(set_to_none=True)
                for k, v in {"loss": loss, **step_logs}.items():
                    sums[k] = sums.get(k, 0.0) + v.detach().float() / o.grad_accum
            lr = scheduler.get_last_lr()[0]
            scheduler.step()
            state.step += 1
            step = state.step
            bar.update(1)

            last = step == o.max_steps
            signalled = _stop_requested(accelerator, stop_request)
            stop = signalled or _time_up(accelerator, cfg, t0)
            if cfg.run.log_every and (step % cfg.run.log_every == 0 or last or stop):
                values = _reduce(accelerator, {**sums, "grad_norm": grad_norm.detach().float()})
                elapsed = time.perf_counter() - t0
                row = {**values, "lr": lr, "samples_per_s": (step - start_step) * o.grad_accum
                       * cfg.data.batch_size * world / max(elapsed, 1e-9), "elapsed_s": elapsed}
                logs.scalars("train", step, row)
                result.losses.append((step, values["loss"]))
                bar.set_postfix(loss=f"{values['loss']:.4f}", lr=f"{lr:.2e}")
            if val_ds is not None and cfg.run.validate_every and (step % cfg.run.validate_every == 0 or last or stop) \
                    and not signalled:
                result.validation = _validate(accelerator, unwrapped, val_ds, cfg, run_dir, step, logs)
            if (cfg.run.checkpoint_every and step % cfg.run.checkpoint_every == 0) or last or stop:
                result.checkpoint = save_checkpoint(accelerator, run_dir, step, keep=cfg.run.keep_checkpoints)
            if stop and not last:
                result.stopped_early = True
                if signalled:
                    result.preempted = stop_request.requested or "SIGTERM"
                    say(f"stopped by {result.preempted} at step {step}: checkpointed; resume with --resume")
                else:
                    say(f"time limit of {cfg.run.time_limit} min reached at step {step}: checkpointed; "
                        "resume with --resume")
                break
    finally:
        stop_request.__exit__(None, None, None)
        _close_loader(batches)
        bar.close()
        logs.close()
    result.bad_pairs = bad.count
    if bad.count:
        say(f"skipped {bad.count} unreadable pair(s) of {n_pairs} (data.skip_bad); listed in {run_dir / BAD_PAIRS}")
    result.steps = state.step
    result.seconds = time.perf_counter() - t0
    if result.checkpoint == run_dir:
        found = latest_checkpoint(run_dir)
        result.checkpoint = found if found is not None else run_dir
    say(f"done: {state.step} steps in {result.seconds:.1f} s; checkpoint {result.checkpoint}")
    accelerator.wait_for_everyone()
    return result


def _adamw(groups: Any, o: Any, say: Callable[[str], None]) -> Any:
    """AdamW with `[optim]`'s settings; `fused` takes torch's one-kernel-per-tensor update (on a
    CPU 1.7 ms a step for the tiny refiner's 2.8 M parameters against 8.2 ms for the per-tensor
    loop, the same formula in another rounding: docs/training.md), falling back to the loop where
    this torch has no fused kernel for the device."""
    kw = dict(lr=o.lr, betas=o.betas, eps=o.eps, weight_decay=o.weight_decay)
    if o.fused:
        # groups of lists (a group's params may be any iterable: read it once)
        groups = [{**g, "params": list(g["params"])} if isinstance(g, dict) else g for g in groups]
        params = [p for g in groups for p in (g["params"] if isinstance(g, dict) else [g])]
        try:  # torch checks the devices when it builds the optimizer (< 2.4) or at its first step
            from torch.utils._foreach_utils import _get_fused_kernels_supported_devices

            devices = set(_get_fused_kernels_supported_devices())
        except ImportError:
            devices = {"cuda"}
        bad = sorted({p.device.type for p in params if p.device.type not in devices or not p.is_floating_point()})
        try:
            if bad:
                raise RuntimeError(f"no fused kernel for {', '.join(bad)} tensors")
            return torch.optim.AdamW(groups, fused=True, **kw)
        except (RuntimeError, ValueError, TypeError) as e:
            say(f"no fused AdamW in torch {torch.__version__} here ({str(e).splitlines()[0][:120]}): "
                "using the per-tensor update")
    return torch.optim.AdamW(groups, **kw)


def _next_batch(batches: Any) -> Any:
    """The next batch; a DataLoader worker's failure re-raised as the one message behind its traceback."""
    try:
        return next(batches)
    except Exception as e:
        text = unwrap_worker_message(str(e))
        if text == str(e):
            raise
        try:
            clean = type(e)(text)
        except Exception:  # noqa: BLE001 - a type that cannot be rebuilt from its message
            clean = DatasetError(text)
        raise clean from None


def _close_loader(batches: Any) -> None:
    """Stop the DataLoader's workers now (a sentinel each, then a join), not at interpreter exit,
    where an error's traceback may still hold the iterator."""
    shutdown = getattr(batches, "_shutdown_workers", None)
    if shutdown is not None:
        shutdown()


def _stop_requested(accelerator: Any, request: StopRequest) -> bool:
    """Whether SIGTERM / Ctrl-C arrived on any process (one collective when distributed)."""
    flag = torch.tensor(float(request.requested is not None), device=accelerator.device)
    if accelerator.num_processes > 1:
        flag = accelerator.reduce(flag, reduction="sum")
    return bool(flag.item() > 0)


class _BadPairs:
    """The pairs `data.skip_bad` skipped: one line each in RUN/bad_pairs.jsonl (kept across
    resumes), a warning the first time each is met, and a stop past `max_share` of the pairs."""

    def __init__(self, run_dir: Path, n_pairs: int, max_share: float, *, enabled: bool,
                 say: Callable[[str], None]) -> None:
        self.path, self.n, self.max_share, self.enabled, self.say = run_dir / BAD_PAIRS, n_pairs, max_share, enabled, say
        self.ids: set[str] = set()
        if enabled and self.path.is_file():
            for line in self.path.read_text(encoding="utf-8").splitlines():
                try:
                    self.ids.add(str(json.loads(line)["pair_id"]))
                except (ValueError, KeyError, TypeError):
                    continue

    @property
    def count(self) -> int:
        return len(self.ids)

    def add(self, step: int, entries: list[tuple[str, str]]) -> None:
        if not self.enabled:
            return
        for pid, msg in entries:
            if pid in self.ids:
                continue
            self.ids.add(pid)
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(json.dumps({"pair_id": pid, "step": step, "error": msg}) + "\n")
            warnings.warn(f"skipping pair {pid}: {msg} (data.skip_bad; listed in {self.path})", MorphgsWarning,
                          stacklevel=2)
        if self.n and self.count > self.max_share * self.n:
            raise TrainingError(f"{self.count} of {self.n} pairs cannot be read (more than data.max_bad_share = "
                                f"{self.max_share}); they are listed in {self.path}")


def _load_newest_good(accelerator: Any, run_dir: Path) -> Path:
    """Load the newest checkpoint that verifies (checksums, then loading it), warning for each
    damaged one skipped; TrainingError when none does."""
    found = list_checkpoints(run_dir)
    if not found:
        raise TrainingError(f"{run_dir}: nothing to resume (no complete checkpoint in {run_dir / 'checkpoints'})")
    damaged = []
    for _, ckpt in reversed(found):
        problem = verify_checkpoint(ckpt)
        if problem is None:
            try:
                accelerator.load_state(str(ckpt))
                return ckpt
            except Exception as e:  # noqa: BLE001 - any failure to load means a damaged checkpoint
                problem = f"cannot be loaded ({type(e).__name__}: {unwrap_worker_message(str(e)).splitlines()[0]})"
        damaged.append(ckpt.name)
        aside = ckpt.with_name(f"damaged-{ckpt.name}")
        if accelerator.is_main_process:
            shutil.rmtree(aside, ignore_errors=True)
            os.replace(ckpt, aside)  # out of the way of the checkpoint this run will write at that step
        warnings.warn(f"checkpoint {ckpt} is damaged ({problem}); skipping it (moved to {aside.name})",
                      MorphgsWarning, stacklevel=2)
    raise TrainingError(f"{run_dir}: no checkpoint verifies ({', '.join(damaged)} damaged), nothing to resume from; "
                        "start over without --resume in a new --out folder (or delete this one)")


def _release(accelerator: Any) -> None:
    """End the run's process group and forget accelerate's process-wide state, so that another
    `train()` in the same process may use other settings (precision, accumulation)."""
    from accelerate.state import AcceleratorState, GradientState

    accelerator.end_training()
    AcceleratorState._reset_state(reset_partial_state=True)
    GradientState._reset_state()


# ---------------------------------------------------------------------------------------------
# pieces of the recipe


def _precision(cfg: TrainConfig) -> str:
    """The accelerate mixed_precision for this machine ("auto": bf16 where the hardware has it)."""
    mp = cfg.run.mixed_precision
    if mp != "auto":
        return mp
    if torch.cuda.is_available() and not cfg.run.cpu:
        return "bf16" if torch.cuda.is_bf16_supported() else "no"
    return "bf16" if _cpu_has_bf16() else "no"


def _use_cpu(cfg: TrainConfig) -> bool:
    """CPU when asked, and for a multi-process launch (torchrun) on a machine without CUDA, so that
    accelerate sets up gloo DDP over the processes instead of running each one alone."""
    multi = int(os.environ.get("WORLD_SIZE", "1")) > 1
    return cfg.run.cpu or (multi and not torch.cuda.is_available())


def _cpu_has_bf16() -> bool:
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def _resolve(run_dir: Path, model: str | None, config: Any, overrides: Mapping[str, Any] | None, resume: bool,
             data: Any) -> ResolvedConfig:
    if not resume:
        return resolve_config(model, config, dict(overrides or {}))
    saved = read_run_file(run_dir)
    try:
        cfg = TrainConfig.from_dict(saved["config"], source=str(run_dir / RUN_FILE))
    except KeyError as e:
        raise TrainingError(f"{run_dir / RUN_FILE}: no {e} in its config") from None
    if config is not None or overrides or (model is not None and model != cfg.model):
        asked = resolve_config(model or cfg.model, config if config is not None else run_dir / "config.toml",
                               dict(overrides or {}))
        if asked.config != cfg:
            raise ConfigError(f"{run_dir}: a run resumes with the config it started with ({run_dir / RUN_FILE}); "
                              "start a new run folder to change it")
    if data is not None and saved.get("data") is not None and Path(data).resolve() != Path(saved["data"]):
        raise TrainingError(f"{run_dir}: started on {saved['data']}, resumed with --data {data}")
    text = (run_dir / "config.toml").read_text(encoding="utf-8") if (run_dir / "config.toml").is_file() else ""
    return ResolvedConfig(cfg, text, str(saved.get("config_source", "")), dict(saved.get("overrides") or {}))


def read_run_file(run_dir: Path) -> dict[str, Any]:
    """The run folder's run.json (config, data, steps), checked.

    Raises:
        FileNotFoundError: no such run folder. TrainingError: no or unreadable run.json.
    """
    path = run_dir / RUN_FILE
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run folder")
    if not path.is_file():
        raise TrainingError(f"{run_dir}: not a run folder (no {RUN_FILE})")
    try:
        return dict(json.loads(path.read_text(encoding="utf-8")))
    except ValueError as e:
        raise TrainingError(f"{path}: unreadable ({e})") from None


def _saved_data(run_dir: Path) -> Path | None:
    d = read_run_file(run_dir).get("data")
    return Path(d) if d else None


def _check_run_dir(run_dir: Path, resume: bool) -> None:
    if resume:
        read_run_file(run_dir)
    elif run_dir.exists() and (not run_dir.is_dir() or any(not is_lock_file(p.name) for p in run_dir.iterdir())):
        raise TrainingError(f"{run_dir}: already exists and is not empty (pass --resume to continue that run, "
                            "or choose a new folder)")


def _start_run_dir(run_dir: Path, resolved: ResolvedConfig, data: Path | None, scenes: Sequence[Any],
                   accelerator: Any) -> None:
    import accelerate

    from morphgs import __version__

    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.toml").write_text(resolved.text, encoding="utf-8")
    info = {
        "model": resolved.config.model,
        "data": str(data.resolve()) if data is not None else None,
        "scenes": [str(Path(s).resolve()) for s in scenes],
        "config_source": resolved.source,
        "overrides": resolved.overrides,
        "config": resolved.config.to_dict(),
        "processes": accelerator.num_processes,
        "device": str(accelerator.device),
        "mixed_precision": accelerator.mixed_precision,
        "versions": {"morphgs": __version__, "torch": torch.__version__, "accelerate": accelerate.__version__},
        "command": sys.argv,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    tmp = run_dir / f".{RUN_FILE}.tmp"
    tmp.write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, run_dir / RUN_FILE)


def _datasets(cfg: TrainConfig, data: Path | None, scenes: Sequence[Any],
              say: Callable[[str], None]) -> tuple[Any, PairDataset | None]:
    d = cfg.data
    configs = list(d.configs) or None
    if d.live:
        train_ds: Any = LivePairs(list(scenes), configs=list(d.live_configs), frames=d.frames, size=d.size or (0, 0),
                                  samples_per_epoch=d.samples_per_epoch, seed=cfg.seed,
                                  threads=d.live_threads or None)
    else:
        if data is None:
            raise TrainingError("training reads a curated folder (--data DIR) unless [data] live = true")
        train_ds = PairDataset(data, "train", d.frames, d.size, train=True, flip=d.flip, resize=d.resize,
                               reference=d.reference, configs=configs)
    val_ds = None
    if data is None:
        say("no curated folder (--data): no validation")
    else:
        if any(r.split == "test" for r in load_records(data)):
            val_ds = PairDataset(data, "test", d.frames, d.size, train=False, resize=d.resize,
                                 reference=d.reference, configs=configs)
        else:
            say(f"{data}: no test pairs, so no validation")
    return train_ds, val_ds


def _checkpoint_hooks(accelerator: Any) -> None:
    """Checkpoints hold what the model's save_trained writes, not accelerate's full weights."""

    def save_hook(models: list[Any], weights: list[Any], output_dir: str) -> None:
        if accelerator.is_main_process:
            for m in models:
                accelerator.unwrap_model(m).save_trained(output_dir)
        weights.clear()

    def load_hook(models: list[Any], input_dir: str) -> None:
        while models:
            accelerator.unwrap_model(models.pop()).load_trained(input_dir)

    accelerator.register_save_state_pre_hook(save_hook)
    accelerator.register_load_state_pre_hook(load_hook)


def _to_device(batch: Mapping[str, Any], device: torch.device) -> dict[str, Any]:
    return {k: v.to(device, non_blocking=True) if torch.is_tensor(v) else v for k, v in batch.items()}


def _reduce(accelerator: Any, values: Mapping[str, Any]) -> dict[str, float]:
    """Mean over processes of scalar tensors (one collective)."""
    keys = sorted(values)
    t = torch.stack([torch.as_tensor(values[k], dtype=torch.float32, device=accelerator.device).reshape(())
                     for k in keys])
    if accelerator.num_processes > 1:
        t = accelerator.reduce(t, reduction="mean")
    return {k: float(v) for k, v in zip(keys, t.tolist())}


def _time_up(accelerator: Any, cfg: TrainConfig, t0: float) -> bool:
    if cfg.run.time_limit <= 0:
        return False
    up = torch.tensor(float(time.perf_counter() - t0 > cfg.run.time_limit * 60.0), device=accelerator.device)
    if accelerator.num_processes > 1:
        up = accelerator.reduce(up, reduction="sum")  # the main process's clock decides for all
    return bool(up.item() > 0)


class _NoBar:
    def update(self, n: int) -> None: ...
    def set_postfix(self, **kw: Any) -> None: ...
    def close(self) -> None: ...


def _progress(enabled: bool, total: int, initial: int) -> Any:
    if not enabled:
        return _NoBar()
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        return _NoBar()
    return tqdm(total=total, initial=initial, desc="train", unit="step", dynamic_ncols=True)


def _validate(accelerator: Any, refiner: Refiner, val_ds: PairDataset | SkipBadPairs, cfg: TrainConfig, run_dir: Path, step: int,
              logs: Logs) -> dict[str, float]:
    """PSNR/SSIM of input vs target and output vs target on the first test clips (centre
    windows), a CSV row and a preview strip; main process only, the others wait."""
    from morphgs.metrics import psnr, ssim

    out: dict[str, float] = {}
    if accelerator.is_main_process:
        was_training = refiner.training
        refiner.eval()
        acc: dict[str, list[float]] = {"psnr_input": [], "psnr_output": [], "ssim_input": [], "ssim_output": []}
        strip = None
        gen = torch.Generator(device=accelerator.device)
        for i in range(min(cfg.run.val_clips or len(val_ds), len(val_ds))):
            s = val_ds[i]
            s.pop("bad", None)  # a skipped test pair (data.skip_bad) was logged when training met it, or is not
            x = s["corrupted"][None].to(accelerator.device)
            ref = s["reference"][None].to(accelerator.device) if "reference" in s else None
            gen.manual_seed(i)
            with torch.no_grad(), accelerator.autocast():
                y = refiner.refine(x, reference=ref, generator=gen).float()
            to01 = lambda t: ((t.float().cpu() + 1) * 0.5).clamp(0, 1).transpose(1, 2)[0]  # noqa: E731
            inp, outp, tgt = to01(x), to01(y), to01(s["clean"][None])
            acc["psnr_input"].append(float(psnr(inp, tgt)))
            acc["psnr_output"].append(float(psnr(outp, tgt)))
            acc["ssim_input"].append(float(ssim(inp, tgt)))
            acc["ssim_output"].append(float(ssim(outp, tgt)))
            if strip is None:
                clips = [c.permute(0, 2, 3, 1).numpy() for c in (inp, outp, tgt)]
                strip = preview_strip(clips, labels=["before", "after", "target"])
        out = {k: float(np.mean(v)) for k, v in acc.items()}
        logs.scalars("val", step, out)
        if strip is not None:
            from PIL import Image

            prev = run_dir / "previews"
            prev.mkdir(exist_ok=True)
            Image.fromarray(strip).save(prev / f"step-{step:07d}.png")
            logs.image("val/before_after_target", step, strip)
        if was_training:
            refiner.train()
    accelerator.wait_for_everyone()
    return out

