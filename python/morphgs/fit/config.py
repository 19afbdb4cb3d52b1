"""The fit config: the 3DGS recipe with pinned defaults, read from and written to TOML.

Defaults are gsplat 1.5.3's `examples/simple_trainer.py` (`default` and `mcmc` configs), which
are the INRIA 3DGS recipe: 30k steps, the position lr 1.6e-4 x scene scale decaying x0.01, the
other lrs of INRIA, L1 x 0.8 + (1 - SSIM) x 0.2, SH degree +1 every 1000 steps up to 3,
densification every 100 steps from step 500 to 15k at a mean NDC gradient of 2e-4, opacity reset
every 3000 steps. One deliberate difference from gsplat 1.5.3: the opacity reset runs (INRIA and
gsplat after 1.5.3 do; 1.5.3 never resets because of a precedence bug) -- set
`default.opacity_reset = false` to reproduce 1.5.3. See docs/fit.md for every value's source.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from morphgs._core import MorphgsError

__all__ = ["DefaultStrategyConfig", "FitConfig", "FitConfigError", "InitConfig", "LearningRates",
           "MCMCConfig", "OutputConfig"]


class FitConfigError(MorphgsError):
    """A fit config file or value that is malformed (names the file and the field)."""


@dataclass
class LearningRates:
    """Adam learning rates per parameter array (means: times the scene scale, decayed
    exponentially to `means_final` times its start over the run)."""

    means: float = 1.6e-4
    means_final: float = 0.01
    quats: float = 1e-3
    scales: float = 5e-3
    opacities: float = 5e-2
    sh0: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20


@dataclass
class DefaultStrategyConfig:
    """gsplat's DefaultStrategy: clone/split/prune and the opacity reset."""

    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    opacity_reset: bool = True
    absgrad: bool = False
    revised_opacity: bool = False
    init_opacity: float = 0.1
    init_scale: float = 1.0


@dataclass
class MCMCConfig:
    """gsplat's MCMCStrategy with a Gaussian cap, and its trainer's regularisers and init."""

    cap_max: int = 1_000_000
    noise_lr: float = 5e5
    refine_start: int = 500
    refine_stop: int = 25_000
    refine_every: int = 100
    min_opacity: float = 0.005
    opacity_reg: float = 0.01
    scale_reg: float = 0.01
    init_opacity: float = 0.5
    init_scale: float = 0.1


@dataclass
class InitConfig:
    """Random initialisation: `random_points` points uniform in the box of the training camera
    centres, each half-side at least the scene scale."""

    random_points: int = 100_000


@dataclass
class OutputConfig:
    """What the run folder gets and how often (steps; 0 = never, except at the end)."""

    eval_every: int = 1000
    checkpoint_every: int = 1000
    preview_every: int = 1000
    progress_every: float = 0.5
    # LPIPS of the held-out renders beside PSNR/SSIM (morphgs.metrics): "auto" (AlexNet when torch
    # and the offline weights are installed, else the column stays empty), "alex", "vgg" or "off"
    lpips: str = "auto"


_SECTIONS: dict[str, type] = {"lr": LearningRates, "default": DefaultStrategyConfig, "mcmc": MCMCConfig,
                              "init": InitConfig, "output": OutputConfig}


@dataclass
class FitConfig:
    """Every knob of `morphgs fit` (docs/fit.md). Scalars at the top, then the sections."""

    steps: int = 30_000
    seed: int = 0
    strategy: str = "default"
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    ssim_lambda: float = 0.2
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_alpha: float = 0.99
    antialiased: bool = False
    # "auto": 1.1 x the largest distance of a training camera centre from their mean (INRIA
    # cameras_extent, gsplat scene_scale); a number overrides it.
    scene_scale: float | str = "auto"
    lr: LearningRates = field(default_factory=LearningRates)
    default: DefaultStrategyConfig = field(default_factory=DefaultStrategyConfig)
    mcmc: MCMCConfig = field(default_factory=MCMCConfig)
    init: InitConfig = field(default_factory=InitConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    # ---- presets ----
    @classmethod
    def preset(cls, name: str) -> FitConfig:
        """"default" (gsplat/INRIA, 30k steps), "mcmc" (the same with MCMCStrategy) or "sparse"
        (a sparse-view fit sized for a CPU: 3000 steps, MCMC capped at 300k Gaussians, SH
        degree 1, evaluation and checkpoints every 500 steps)."""
        if name == "default":
            return cls()
        if name == "mcmc":
            return cls(strategy="mcmc")
        if name == "sparse":
            c = cls(steps=3000, strategy="mcmc", sh_degree=1)
            c.mcmc.cap_max = 300_000
            c.init.random_points = 50_000
            c.output = OutputConfig(eval_every=500, checkpoint_every=500, preview_every=500)
            return c
        raise FitConfigError(f"unknown fit preset {name!r}: expected default, mcmc or sparse")

    # ---- dict / TOML ----
    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["background"] = list(self.background)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "config") -> FitConfig:
        """Build from a dict (a parsed TOML file); unknown keys and wrong types are errors that
        name the field."""
        if not isinstance(d, dict):
            raise FitConfigError(f"{source}: expected a table of settings")
        cfg = cls()
        for key, value in d.items():
            if key in _SECTIONS:
                if not isinstance(value, dict):
                    raise FitConfigError(f"{source}: [{key}] must be a table")
                sec = getattr(cfg, key)
                for k2, v2 in value.items():
                    _set(sec, k2, v2, f"{source}: {key}.{k2}")
            else:
                _set(cfg, key, value, f"{source}: {key}")
        cfg.validate(source=source)
        return cfg

    @classmethod
    def load(cls, path: str | Path) -> FitConfig:
        """Read a TOML file (a partial file overrides the defaults it names).

        Raises:
            FileNotFoundError: no such file. FitConfigError: bad TOML or values (names them).
        """
        p = Path(path)
        text = p.read_text(encoding="utf-8")
        try:
            data = _toml_loads(text)
        except ValueError as e:
            raise FitConfigError(f"{p}: not valid TOML ({e})") from None
        return cls.from_dict(data, source=str(p))

    def to_toml(self) -> str:
        """The config as a TOML file (every value written, so a run folder records it all)."""
        lines = ["# morphgs fit config (docs/fit.md). Defaults: gsplat 1.5.3 simple_trainer = INRIA 3DGS,",
                 "# with the opacity reset on (default.opacity_reset = false reproduces gsplat 1.5.3).", ""]
        for f in dataclasses.fields(self):
            if f.name in _SECTIONS:
                continue
            lines.append(f"{f.name} = {_toml_value(getattr(self, f.name))}")
        for name in _SECTIONS:
            lines += ["", f"[{name}]"]
            sec = getattr(self, name)
            for f in dataclasses.fields(sec):
                lines.append(f"{f.name} = {_toml_value(getattr(sec, f.name))}")
        return "\n".join(lines) + "\n"

    # ---- checks and the native form ----
    def validate(self, *, source: str = "config") -> None:
        """Range checks the native side does not make (it checks the rest)."""
        for obj, prefix in [(self, "")] + [(getattr(self, k), f"{k}.") for k in _SECTIONS]:
            for f in dataclasses.fields(obj):
                v = getattr(obj, f.name)
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    continue
                if not math.isfinite(v) or v < 0:
                    raise FitConfigError(f"{source}: {prefix}{f.name} must be a finite number >= 0, got {v}")
        if self.strategy not in ("default", "mcmc"):
            raise FitConfigError(f"{source}: strategy must be 'default' or 'mcmc', got {self.strategy!r}")
        if self.steps < 1:
            raise FitConfigError(f"{source}: steps must be >= 1, got {self.steps}")
        if not 0 <= self.sh_degree <= 3:
            raise FitConfigError(f"{source}: sh_degree must be 0..3, got {self.sh_degree}")
        if isinstance(self.scene_scale, str):
            if self.scene_scale != "auto":
                raise FitConfigError(f"{source}: scene_scale must be 'auto' or a number, got {self.scene_scale!r}")
        elif not (math.isfinite(self.scene_scale) and self.scene_scale > 0):
            raise FitConfigError(f"{source}: scene_scale must be positive, got {self.scene_scale}")
        if len(self.background) != 3:
            raise FitConfigError(f"{source}: background must be 3 numbers")
        if self.init.random_points < 1:
            raise FitConfigError(f"{source}: init.random_points must be >= 1")
        for k in ("eval_every", "checkpoint_every", "preview_every"):
            if getattr(self.output, k) < 0:
                raise FitConfigError(f"{source}: output.{k} must be >= 0")
        if self.output.lpips not in ("auto", "alex", "vgg", "off"):
            raise FitConfigError(f"{source}: output.lpips must be 'auto', 'alex', 'vgg' or 'off', got {self.output.lpips!r}")
        if self.output.progress_every < 0:
            raise FitConfigError(f"{source}: output.progress_every must be >= 0")

    @property
    def init_opacity(self) -> float:
        return self.mcmc.init_opacity if self.strategy == "mcmc" else self.default.init_opacity

    @property
    def init_scale(self) -> float:
        return self.mcmc.init_scale if self.strategy == "mcmc" else self.default.init_scale

    def native(self, scene_scale: float) -> dict[str, Any]:
        """The dict `_core.Trainer` reads (scene_scale resolved)."""
        d = self.to_dict()
        for k in ("init", "output"):
            d.pop(k)
        for k in ("init_opacity", "init_scale"):
            d["default"].pop(k)
            d["mcmc"].pop(k)
        d["scene_scale"] = float(scene_scale)
        return d


def _set(obj: Any, key: str, value: Any, where: str) -> None:
    fields = {f.name: f for f in dataclasses.fields(obj)}
    if key not in fields:
        raise FitConfigError(f"{where}: unknown setting (known: {', '.join(sorted(fields))})")
    current = getattr(obj, key)
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise FitConfigError(f"{where}: expected true or false, got {value!r}")
    elif isinstance(current, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise FitConfigError(f"{where}: expected an integer, got {value!r}")
    elif isinstance(current, float) and not (key == "scene_scale"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise FitConfigError(f"{where}: expected a number, got {value!r}")
        value = float(value)
    elif key == "scene_scale":
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise FitConfigError(f"{where}: expected 'auto' or a number, got {value!r}")
        value = value if isinstance(value, str) else float(value)
    elif key == "background":
        if not isinstance(value, (list, tuple)) or len(value) != 3 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise FitConfigError(f"{where}: expected three numbers, got {value!r}")
        value = tuple(float(v) for v in value)
    elif isinstance(current, str):
        if not isinstance(value, str):
            raise FitConfigError(f"{where}: expected a string, got {value!r}")
    setattr(obj, key, value)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def _toml_loads(text: str) -> dict[str, Any]:
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover - Python 3.10
        try:
            import tomli as tomllib
        except ImportError:
            raise ImportError("reading TOML on Python 3.10 needs tomli: pip install 'morphgs[fit]'") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(str(e)) from None
