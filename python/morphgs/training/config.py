"""The run config of `morphgs train`: which model, and the [data], [optim], [run] and [model]
sections (configs/tiny.toml documents every key).

Resolution: the model's shipped config (`morphgs/configs/<model>.toml`), then the user's
`--config` file merged over it (tables key by key), then `--set SECTION.KEY=VALUE` overrides and
the shorthand flags. The text of the user's file (or of the shipped one) is kept as written and
saved into the run folder; the resolved values go to `run.json`. Torch-free.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from morphgs.configfile import ConfigError, config_from_dict, load_toml, loads, merge

__all__ = ["DataConfig", "OptimConfig", "ResolvedConfig", "RunConfig", "TrainConfig", "resolve_config"]

@dataclass(frozen=True)
class DataConfig:
    """[data]: what the loop reads."""

    frames: int = 16
    size: tuple[int, int] | None = (128, 192)
    resize: tuple[int, int] | None = None
    flip: bool = True
    reference: int = 0
    batch_size: int = 1
    num_workers: int = 2
    configs: tuple[str, ...] = ()
    live: bool = False
    live_configs: tuple[str, ...] = ("morphological",)
    samples_per_epoch: int = 1024
    live_threads: int = 0
    skip_bad: bool = False
    max_bad_share: float = 0.1

    def __post_init__(self) -> None:
        if self.frames < 1 or self.batch_size < 1 or self.num_workers < 0 or self.reference < 0:
            raise ValueError("frames and batch_size must be >= 1, num_workers and reference >= 0")
        if not 0.0 <= self.max_bad_share <= 1.0:
            raise ValueError(f"max_bad_share is a share of the pairs in [0, 1], got {self.max_bad_share}")
        if self.live and self.size is None:
            raise ValueError("live pairs need a size (the rendered frame size)")


@dataclass(frozen=True)
class OptimConfig:
    """[optim]: AdamW and its schedule (the paper's settings as defaults, lr aside)."""

    lr: float = 3e-4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 1e-2
    eps: float = 1e-8
    schedule: str = "cosine"
    warmup: float = 0.05
    grad_clip: float = 1.0
    grad_accum: int = 1
    max_steps: int = 2000
    fused: bool = True

    def __post_init__(self) -> None:
        if self.lr <= 0 or self.max_steps < 1 or self.grad_accum < 1:
            raise ValueError("lr must be > 0, max_steps and grad_accum >= 1")
        if not 0.0 <= self.warmup < 1.0:
            raise ValueError(f"warmup is a share of max_steps in [0, 1), got {self.warmup}")
        if self.schedule not in ("cosine", "linear", "constant"):
            raise ValueError(f"schedule must be cosine, linear or constant, got {self.schedule!r}")
        if self.grad_clip < 0:
            raise ValueError("grad_clip must be >= 0 (0: no clipping)")


@dataclass(frozen=True)
class RunConfig:
    """[run]: precision, checkpoints, validation, logs."""

    mixed_precision: str = "auto"
    checkpoint_every: int = 250
    keep_checkpoints: int = 2
    validate_every: int = 250
    val_clips: int = 4
    log_every: int = 10
    time_limit: float = 0.0
    cpu: bool = False
    threads: int = 0

    def __post_init__(self) -> None:
        if self.mixed_precision not in ("auto", "no", "bf16", "fp16"):
            raise ValueError(f"mixed_precision must be auto, no, bf16 or fp16, got {self.mixed_precision!r}")
        if min(self.checkpoint_every, self.validate_every, self.log_every) < 0 or self.keep_checkpoints < 1:
            raise ValueError("checkpoint_every, validate_every, log_every must be >= 0 (0: never); "
                             "keep_checkpoints >= 1")
        if self.time_limit < 0 or self.val_clips < 0 or self.threads < 0:
            raise ValueError("time_limit (minutes), val_clips and threads must be >= 0")


@dataclass(frozen=True)
class TrainConfig:
    """Every resolved setting of a run."""

    model: str
    seed: int
    data: DataConfig
    optim: OptimConfig
    run: RunConfig
    model_config: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        """Plain values (as run.json stores them)."""
        d = asdict(self)
        d["model_config"] = dict(self.model_config)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str) -> TrainConfig:
        """Back from `to_dict` (arrays as lists are fine)."""
        return _to_config({"seed": d["seed"], "data": d["data"], "optim": d["optim"], "run": d["run"],
                           "model": {"name": d["model"], **dict(d.get("model_config") or {})}}, source)


@dataclass(frozen=True)
class ResolvedConfig:
    """A resolved config and the text it came from."""

    config: TrainConfig
    text: str
    source: str
    overrides: dict[str, Any]


def _to_config(d: dict[str, Any], source: str) -> TrainConfig:
    unknown = sorted(k for k in d if k not in ("seed", "data", "optim", "run", "model"))
    if unknown:
        raise ConfigError(f"{source}: unknown key or table {unknown[0]!r} (known: seed, [data], [optim], [run], "
                          "[model])")
    table = d.get("model")
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: [model] must be a table with a name, got {table!r}")
    model_config = dict(table)
    name = model_config.pop("name", None)
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{source}: [model] name must name a registered model, got {name!r}")
    seed = d.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{source}: seed must be an integer >= 0, got {seed!r}")
    return TrainConfig(
        model=name, seed=seed,
        data=config_from_dict(DataConfig, d.get("data"), section="data", source=source),
        optim=config_from_dict(OptimConfig, d.get("optim"), section="optim", source=source),
        run=config_from_dict(RunConfig, d.get("run"), section="run", source=source),
        model_config=model_config,
    )


def resolve_config(model: str | None, config: str | os.PathLike[str] | None,
                   overrides: dict[str, Any] | None = None) -> ResolvedConfig:
    """The run config from a model name, an optional config file and overrides.

    The model is `model` if given, else the file's `[model] name`, else "tiny"; its shipped config
    supplies every key the file leaves out.

    Raises:
        FileNotFoundError: no such config file. ConfigError: bad TOML, unknown keys, wrong types.
        UnknownModelError: no such model.
    """
    from morphgs.models.registry import default_config_text

    user: dict[str, Any] = {}
    text = None
    source = "command line"
    if config is not None:
        text, user = load_toml(config)
        source = str(config)
    user_model = user.get("model")
    file_name = user_model.get("name") if isinstance(user_model, dict) else None
    name = model or (file_name if isinstance(file_name, str) else None) or "tiny"
    shipped_text = default_config_text(name)
    merged = merge(loads(shipped_text, source=f"morphgs/configs/{name}.toml"), user)
    merged = merge(merged, dict(overrides or {}))
    if isinstance(merged.get("model"), dict):
        merged["model"] = {**merged["model"], "name": name}
    cfg = _to_config(merged, source)
    return ResolvedConfig(cfg, text if text is not None else shipped_text,
                          source if config is not None else f"morphgs/configs/{name}.toml (shipped)",
                          dict(overrides or {}))


def config_path_for(run_dir: str | os.PathLike[str]) -> Path:
    """Where a run keeps its config as written."""
    return Path(run_dir) / "config.toml"
