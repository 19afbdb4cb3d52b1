"""The paper's 3D perturbations (SPEC §2): `PerturbConfig`, its presets and `perturb`.

Six operations act on every Gaussian independently: position jitter (spatial), photometric and
opacity noise (radiometric), random pruning, scale and rotation noise (morphological). A
`PerturbConfig` holds one parameter per operation; `None` (or a zero noise scale) disables it.
The noise is drawn from a counter-based generator keyed by (seed, op, Gaussian index), so the
result is bit-identical for any thread count and Gaussian i gets the same noise in an op
whichever other ops run (see docs/perturbation.md).
"""

from __future__ import annotations

import dataclasses
import json
import math
import operator
from collections.abc import Mapping
from typing import Any, Literal, overload

import numpy as np
import numpy.typing as npt

from morphgs._core import GaussianScene, _perturb

#: Preset names, in the paper's order.
PRESETS: tuple[str, ...] = ("spatial", "radiometric", "morphological", "naive")

#: The fields of a config, in SPEC §2 order.
FIELDS: tuple[str, ...] = (
    "position_jitter",
    "color_noise",
    "opacity_noise",
    "prune",
    "scale_noise",
    "rotation_noise",
)
_NOISE_FIELDS = tuple(f for f in FIELDS if f != "prune")
_CATEGORIES: dict[str, tuple[str, ...]] = {
    "spatial": ("position_jitter",),
    "radiometric": ("color_noise", "opacity_noise"),
    "morphological": ("prune", "scale_noise", "rotation_noise"),
    "naive": FIELDS,
}


@dataclasses.dataclass(frozen=True)
class PerturbConfig:
    """Parameters of the six perturbation operations; `None` disables an operation.

    The defaults are the paper's (all six enabled, i.e. the `naive` preset); use
    `PerturbConfig.preset(name)` for the paper's categories.

    Attributes:
        position_jitter: gamma_xyz; centres move by N(0, (gamma_xyz * E_avg)^2), E_avg the mean
            extent of the input scene's centres over x, y, z.
        color_noise: sigma_color, on the DC colour c = 0.5 + C0*sh0, clamped to [0, 1].
        opacity_noise: sigma_opac, on the activated opacity, clamped to [1e-4, 1 - 1e-4].
        prune: p_prune, the probability of removing each Gaussian, in [0, 1].
        scale_noise: sigma_scale, on the linear axis scales, floored at 1e-6.
        rotation_noise: sigma_rot, on the normalised quaternion, renormalised after.
        name: the preset this config came from (informational; not compared or serialised).

    Raises:
        ValueError: a noise scale is negative or not finite, or prune is outside [0, 1]
            (the message names the field).
        TypeError: a field is not a number or None.
    """

    position_jitter: float | None = 0.002
    color_noise: float | None = 0.05
    opacity_noise: float | None = 0.05
    prune: float | None = 0.5
    scale_noise: float | None = 0.01
    rotation_noise: float | None = 0.01
    name: str | None = dataclasses.field(default=None, compare=False)

    def __post_init__(self) -> None:
        for field in FIELDS:
            value = getattr(self, field)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise TypeError(f"{field} must be a number or None, got {type(value).__name__}")
            v = float(value)
            if field == "prune":
                if not 0.0 <= v <= 1.0:
                    raise ValueError(f"prune must be a probability in [0, 1], got {value!r}")
            elif not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{field} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, field, v)

    @classmethod
    def preset(cls, name: str) -> PerturbConfig:
        """The paper's presets at its defaults; the other operations are disabled.

        Args:
            name: "spatial" (position jitter), "radiometric" (colour + opacity noise),
                "morphological" (pruning + scale + rotation noise; the paper's recommended
                regulariser) or "naive" (all six at once).

        Raises:
            ValueError: an unknown name (the message lists the valid ones).
        """
        if name not in _CATEGORIES:
            raise ValueError(f"unknown preset {name!r}; valid presets: {', '.join(PRESETS)}")
        paper = cls()
        kept = _CATEGORIES[name]
        return cls(**{f: getattr(paper, f) if f in kept else None for f in FIELDS}, name=name)

    @property
    def enabled(self) -> tuple[str, ...]:
        """The operations this config runs (a zero noise scale or prune counts as disabled)."""
        return tuple(f for f in FIELDS if getattr(self, f))

    def to_dict(self) -> dict[str, float | None]:
        """The six parameters as a plain dict (None for a disabled operation)."""
        return {f: getattr(self, f) for f in FIELDS}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PerturbConfig:
        """Inverse of `to_dict`; missing keys mean None (disabled).

        Raises:
            ValueError: an unknown key (the message lists the valid ones) or an invalid value.
        """
        unknown = sorted(set(data) - set(FIELDS))
        if unknown:
            raise ValueError(
                f"unknown perturbation field(s) {', '.join(map(repr, unknown))}; "
                f"valid fields: {', '.join(FIELDS)}"
            )
        return cls(**{f: data.get(f) for f in FIELDS})

    def to_json(self) -> str:
        """`to_dict` as JSON (what datasets record)."""
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> PerturbConfig:
        """Inverse of `to_json`.

        Raises:
            ValueError: invalid JSON, not an object, or an invalid config.
        """
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError(f"a perturbation config must be a JSON object, got {type(data).__name__}")
        return cls.from_dict(data)

    def scaled(self, k: float) -> PerturbConfig:
        """A config of strength k, for strength sweeps and curricula.

        Every enabled noise scale is multiplied by k and the pruning probability becomes
        min(k * prune, 1). So `scaled(0)` is the identity (no noise, nothing pruned), `scaled(1)`
        is this config, and every operation grows monotonically with k. Disabled operations stay
        disabled.

        Args:
            k: the strength, a finite number >= 0.

        Raises:
            ValueError: k is negative or not finite.
        """
        kf = float(k)
        if not (math.isfinite(kf) and kf >= 0.0):
            raise ValueError(f"k must be a finite number >= 0, got {k!r}")
        values: dict[str, float | None] = {}
        for f in FIELDS:
            v = getattr(self, f)
            if v is None:
                values[f] = None
            elif f == "prune":
                values[f] = min(kf * v, 1.0)
            else:
                values[f] = kf * v
        return PerturbConfig.from_dict(values)


def as_config(config: str | PerturbConfig | Mapping[str, Any]) -> PerturbConfig:
    """Resolve what users pass wherever a config is expected.

    Args:
        config: a preset name, a `PerturbConfig`, or a dict as `PerturbConfig.to_dict` writes.

    Raises:
        ValueError: an unknown preset or an invalid dict.
        TypeError: anything else.
    """
    if isinstance(config, PerturbConfig):
        return config
    if isinstance(config, str):
        return PerturbConfig.preset(config)
    if isinstance(config, Mapping):
        return PerturbConfig.from_dict(config)
    raise TypeError(
        f"config must be a preset name, a PerturbConfig or a dict, got {type(config).__name__}"
    )


def check_seed(seed: Any) -> int:
    """`seed` as an int in the u64 range (TypeError / ValueError naming the problem otherwise)."""
    if isinstance(seed, bool):
        raise TypeError("seed must be an int, got bool")
    try:
        s = operator.index(seed)
    except TypeError:
        raise TypeError(f"seed must be an int, got {type(seed).__name__}") from None
    if not 0 <= s < 2**64:
        raise ValueError(f"seed must be in [0, 2**64), got {s}")
    return s


@overload
def perturb(
    scene: GaussianScene,
    config: str | PerturbConfig | Mapping[str, Any] = ...,
    *,
    seed: int,
    return_mask: Literal[False] = ...,
) -> GaussianScene: ...
@overload
def perturb(
    scene: GaussianScene,
    config: str | PerturbConfig | Mapping[str, Any] = ...,
    *,
    seed: int,
    return_mask: Literal[True],
) -> tuple[GaussianScene, npt.NDArray[np.bool_]]: ...
def perturb(
    scene: GaussianScene,
    config: str | PerturbConfig | Mapping[str, Any] = "morphological",
    *,
    seed: int,
    return_mask: bool = False,
) -> GaussianScene | tuple[GaussianScene, npt.NDArray[np.bool_]]:
    """Perturb a scene's Gaussians (SPEC §2); the input scene is left untouched.

    Args:
        scene: the clean scene.
        config: a preset name ("spatial", "radiometric", "morphological", "naive"), a
            `PerturbConfig`, or a dict of its fields. Default: the paper's recommended
            morphological preset.
        seed: the seed (an int in [0, 2**64)); the same seed gives bit-identical output on any
            number of threads.
        return_mask: also return the (N,) boolean keep-mask of the pruning, so that
            `perturbed` row r is the original Gaussian `np.flatnonzero(mask)[r]`.

    Returns:
        The perturbed GaussianScene (SH bands above the DC term and extras are carried over
        unchanged for the survivors), or (scene, mask) with return_mask=True.

    Raises:
        ValueError: an invalid config or seed (the message names the field).
        TypeError: a wrong type for scene, config or seed.
    """
    if not isinstance(scene, GaussianScene):
        raise TypeError(f"scene must be a GaussianScene, got {type(scene).__name__}")
    cfg = as_config(config)
    s = check_seed(seed)
    result: Any = _perturb(
        scene,
        position_jitter=cfg.position_jitter,
        color_noise=cfg.color_noise,
        opacity_noise=cfg.opacity_noise,
        prune=cfg.prune,
        scale_noise=cfg.scale_noise,
        rotation_noise=cfg.rotation_noise,
        seed=s,
        return_mask=return_mask,
    )
    return result  # type: ignore[no-any-return]
