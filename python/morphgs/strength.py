"""The strength parameterisation: one smooth, scene-aware severity knob s >= 0 per family.

`PerturbConfig.scaled(k)` (the `NAME@K` form) multiplies the paper's absolute parameters
linearly and clips pruning at 1, so `morphological@2` prunes every Gaussian (a cliff), and its
scale noise is an absolute sigma in scene units whatever the scene's size. `Strength` is the
calibration-friendly alternative (docs/perturbation.md, "Strength"). At strength s, with the
family's base values b (the values at s = 1, `BASE`, or the user's own):

| op | formula at strength s |
|---|---|
| keep | each Gaussian kept with probability keep = b_keep ** s (so prune = 1 - b_keep ** s < 1 for every finite s; a larger s prunes a superset) |
| log_scale | log s_i' = log s_i + s * b * z_i per axis, z ~ N(0, 1): relative to each Gaussian's own scale |
| rotation | q_i' = exp(omega_i) * q_i, omega_i = s * b / sqrt(3) * z_i, z ~ N(0, I3): an isotropic rotation of RMS angle s * b radians |
| position | the kernel's position jitter with gamma = s * b (a fraction of the scene extent E_avg) |
| color | the kernel's DC-colour noise with sigma = s * b |
| opacity | the kernel's opacity noise with sigma = s * b (activated opacity, clamped) |

The sparse-view ops (issue 36; docs/artifacts.md) mimic how a fit from a few training views fails,
from "virtual training cameras": every `train_every`-th camera of the pair's path (the regime's K).
They keep those views close to clean and break the views between them:

| op | at strength s |
|---|---|
| depth | each Gaussian slides along the ray of its nearest training camera by a factor exp(s * b * z), scales with it (the same footprint there) |
| view_color | SH noise of sigma s * b on bands 1-3 that vanishes at the directions of the nearest training cameras |
| needles | a fraction 1 - (1 - b) ** s of Gaussians become needles along their training ray |
| holes | a fraction 1 - (1 - b) ** s of the cells of a grid (edge 0.05 E_avg) lose their Gaussians |
| dilate | every log scale + s * b |
| floaters | min(10, s * b) new Gaussians per thousand training pixels, near the training cameras, coloured from the pixel they cover |
| shatter | v = min(8, s * b): each Gaussian removed with probability 1 - exp(-v), the training views' pixels re-made as small fragments on their rays at depth d exp(0.3 v z) (`morphgs.shatter`) |
| popping | a Gaussian of weight w (opacity x size) pops with probability 1 - (1 - b) ** (s * w): hidden from a cone of views between two training views |
| haze | min(16, s * b) x 250 faint, large Gaussians per training view beside the training cameras (`morphgs.haze`) |
| veil | min(16, s * b) x 100 faint, wide Gaussians per training view (at most) where every training view that sees them shows their colour (`morphgs.veil`) |

Popping's cones ride along as the scene extras `POPPING_EXTRAS`; every render honours them frame by frame.

Every op is the identity at s = 0, every op's noise grows continuously with s, and the same seed
gives the same z at every s (common random numbers), so severity is a smooth function of s.
Every op runs in the Rust perturb kernel (op ids 4, 1, 2, 3 for keep, position, colour and
opacity; 7 and 8 for log_scale and rotation; 10-18 for the sparse-view ops), keyed by the
Gaussian's index in the input scene (shatter's fragments by their training pixel's), with exactly rounded float operations only: the same bytes
for any thread count and on any CPU.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from morphgs import noise
from morphgs._core import GaussianScene

__all__ = ["BASE", "BLUR_MAX_SIGMA", "CLASSIC_OPS", "FAMILIES", "OPS", "POPPING_EXTRAS", "SPARSE_OPS", "TRAIN_EVERY",
           "Blur2d", "Strength"]

#: The ops of the paper's families, in application order.
CLASSIC_OPS: tuple[str, ...] = ("position", "color", "opacity", "keep", "log_scale", "rotation")
#: The sparse-view ops (applied first, from the virtual training cameras).
SPARSE_OPS: tuple[str, ...] = ("depth", "view_color", "needles", "holes", "dilate", "floaters", "shatter", "popping",
                                "haze", "veil")
#: Every op of the strength parameterisation.
OPS: tuple[str, ...] = CLASSIC_OPS + SPARSE_OPS
#: The sparse-view ops of the one native pass `_artifacts` (shatter follows it, popping draws its
#: caps after both).
ARTIFACT_OPS: tuple[str, ...] = ("depth", "view_color", "needles", "holes", "dilate", "floaters")
#: The sparse-view ops that need training cameras (all but holes and dilate).
CAMERA_OPS: tuple[str, ...] = ("depth", "view_color", "needles", "floaters", "shatter", "popping", "haze", "veil")
#: The sparse-view ops whose value is a fraction, 1 - (1 - b) ** s at strength s.
FRACTION_OPS: tuple[str, ...] = ("needles", "holes", "popping")
#: The scene extras that carry the popping caps (axis x, y, z and cap height h; docs/artifacts.md):
#: a scene holding them renders with them, frame by frame.
POPPING_EXTRAS: tuple[str, ...] = ("popping_x", "popping_y", "popping_z", "popping_h")
#: Default spacing of the virtual training cameras along a pair's path (every 8th camera).
TRAIN_EVERY = 8

#: Base values (strength 1) of every op. keep = 0.5 is the paper's p_prune; 0.5 in log scale is a
#: factor e^0.5 = 1.65 at one sigma; rotation 0.5 rad (29 degrees) RMS; position, colour and
#: opacity are the paper's sigmas. Sparse-view ops: depth 0.3 (a factor e^0.3 = 1.35 along the
#: ray at one sigma), view_color 0.3 (SH units), needles 0.2 and holes 0.1 (fractions), dilate 0.3
#: (a factor 1.35 on every scale), floaters 0.2 per thousand training pixels, shatter 1.0 (63 % of
#: the Gaussians replaced by fragments at a log-depth spread of 0.3), popping 0.3 (the share of
#: median-sized opaque Gaussians that pop), haze 1.0 (250 faint Gaussians per training view beside
#: the cameras, `morphgs.haze`: the population measured in real sparse fits), veil 1.0 (at most 100
#: Gaussians per training view that every training view seeing them shows in their own colour,
#: `morphgs.veil`: the backdrop a real object capture's sparse fit leaves at the object's depth).
BASE: dict[str, float] = {"position": 0.002, "color": 0.05, "opacity": 0.05, "keep": 0.5,
                          "log_scale": 0.5, "rotation": 0.5, "depth": 0.3, "view_color": 0.3, "needles": 0.2,
                          "holes": 0.1, "dilate": 0.3, "floaters": 0.2, "shatter": 1.0,
                          "popping": 0.3, "haze": 1.0, "veil": 1.0}

#: The families and their ops: the paper's four (unchanged), one per sparse-view op, and
#: `sparse-like`, the sparse-view ops together.
FAMILIES: dict[str, tuple[str, ...]] = {
    "spatial": ("position",),
    "radiometric": ("color", "opacity"),
    "morphological": ("keep", "log_scale", "rotation"),
    "naive": CLASSIC_OPS,
    **{op: (op,) for op in SPARSE_OPS},
    "sparse-like": ("depth", "view_color", "needles", "holes", "floaters"),
}
#: Bounds of the effective values the kernel takes (larger strengths saturate there).
_LIMITS = {"depth": 4.0, "dilate": 8.0, "floaters": 10.0, "shatter": 8.0, "haze": 16.0, "veil": 16.0}


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{what} must be a number, got {type(value).__name__}")
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{what} must be a finite number >= 0, got {value!r}")
    return v


@dataclasses.dataclass(frozen=True)
class Strength:
    """A family at strength s (see the module docstring for the formulas).

    Attributes:
        family: "spatial", "radiometric", "morphological" or "naive" (informational once `ops`
            is given; it names the config).
        strength: s, a finite number >= 0.
        ops: the base value (at s = 1) of each enabled op; ops not listed are disabled. Default:
            the family's ops at `BASE`, so the preset's proportions are kept.
        train_every: the virtual training cameras of the sparse-view ops: every `train_every`-th
            camera of the pair's path, from the first (the regime's K).

    Raises:
        ValueError: an unknown family or op, a negative or non-finite value, keep outside (0, 1].
        TypeError: a value that is not a number.
    """

    family: str
    strength: float = 1.0
    ops: Mapping[str, float] | None = None
    train_every: int = TRAIN_EVERY

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ValueError(f"unknown family {self.family!r}; valid families: {', '.join(FAMILIES)}")
        object.__setattr__(self, "strength", _number(self.strength, "strength"))
        ops = dict(self.ops) if self.ops is not None else {k: BASE[k] for k in FAMILIES[self.family]}
        unknown = sorted(set(ops) - set(OPS))
        if unknown:
            raise ValueError(f"unknown strength op(s) {', '.join(map(repr, unknown))}; valid ops: {', '.join(OPS)}")
        clean = {k: _number(ops[k], f"ops.{k}") for k in OPS if k in ops and ops[k] is not None}
        if "keep" in clean and not 0.0 < clean["keep"] <= 1.0:
            raise ValueError(f"ops.keep must be a keep fraction in (0, 1], got {clean['keep']!r}")
        for k in FRACTION_OPS:
            if k in clean and clean[k] >= 1.0:
                raise ValueError(f"ops.{k} must be a fraction in [0, 1), got {clean[k]!r}")
        every = self.train_every
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise ValueError(f"train_every must be an integer >= 1, got {every!r}")
        object.__setattr__(self, "train_every", int(every))
        object.__setattr__(self, "ops", clean)

    @property
    def base(self) -> dict[str, float]:
        """The enabled ops and their base values (at strength 1)."""
        assert self.ops is not None
        return dict(self.ops)

    def at(self, strength: float) -> Strength:
        """The same family and ops at another strength."""
        return Strength(self.family, strength, self.ops, self.train_every)

    def only(self, op: str) -> Strength:
        """This config with every op but `op` disabled (for each op's share of the error)."""
        if op not in self.base:
            raise ValueError(f"op {op!r} is not enabled in this config ({', '.join(self.base)})")
        return Strength(self.family, self.strength, {op: self.base[op]}, self.train_every)

    @property
    def needs_cameras(self) -> bool:
        """Whether an enabled op needs the pair's cameras (depth, view_color, needles, floaters,
        shatter, popping, haze, veil)."""
        return any(op in self.base for op in CAMERA_OPS)

    def values(self) -> dict[str, float]:
        """The effective parameters at this strength: keep fraction, sigmas, RMS angle, the
        sparse-view ops' sigmas and fractions."""
        s = self.strength
        out = {}
        for k, b in self.base.items():
            if k == "keep":
                out[k] = b ** s
            elif k in FRACTION_OPS:
                out[k] = 1.0 - (1.0 - b) ** s
            else:
                out[k] = min(s * b, _LIMITS.get(k, math.inf))
        return out

    def to_dict(self) -> dict[str, Any]:
        """{"kind": "strength", "family", "strength", "ops"} (what configs and manifests record),
        and "train_every" when a sparse-view op uses the training cameras."""
        d = {"kind": "strength", "family": self.family, "strength": self.strength, "ops": self.base}
        if self.needs_cameras:
            d["train_every"] = self.train_every
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Strength:
        """Inverse of `to_dict` ("kind" and "name" are ignored; "ops" defaults to the family's).

        Raises:
            ValueError: a missing family, an unknown key or an invalid value (named).
        """
        unknown = sorted(set(data) - {"kind", "name", "family", "strength", "ops", "train_every"})
        if unknown:
            raise ValueError(f"unknown strength config key(s) {', '.join(map(repr, unknown))}; "
                             "valid keys: family, strength, ops, train_every")
        if "family" not in data:
            raise ValueError("a strength config needs a 'family'")
        ops = data.get("ops")
        if ops is not None and not isinstance(ops, Mapping):
            raise ValueError("'ops' must be an object of op base values")
        return cls(str(data["family"]), data.get("strength", 1.0), ops, data.get("train_every", TRAIN_EVERY))

    def train_cameras(self, cameras: Any) -> Any:
        """The virtual training cameras of a pair's path: every `train_every`-th, from the first."""
        from morphgs.camera import Cameras

        cams = cameras if isinstance(cameras, Cameras) else Cameras.from_list(list(cameras))
        return cams[:: self.train_every]

    def _train_views(self, cameras: Any, train_cameras: Any) -> Any:
        """The virtual training cameras: `train_cameras` as given, else every `train_every`-th
        of `cameras`."""
        from morphgs.camera import Cameras

        if train_cameras is not None:
            return train_cameras if isinstance(train_cameras, Cameras) else Cameras.from_list(list(train_cameras))
        return self.train_cameras(cameras)

    def apply(self, scene: GaussianScene, *, seed: int, return_mask: bool = False, cameras: Any = None,
              train_cameras: Any = None) -> Any:
        """The perturbed copy of `scene` (seeded; the same bytes for any thread count and CPU).

        The sparse-view ops run first (`_artifacts`, ops 10-14; their training cameras are every
        `train_every`-th of `cameras`, the floaters coloured from clean renders of them), then
        shatter (`morphgs.shatter`), then haze appends its Gaussians (`morphgs.haze`; the paper's
        ops then treat them as any other), then the veil's (`morphgs.veil`, drawn from the clean
        scene's training views), then popping draws its caps on their output (`_popping`, op 15;
        the caps become the scene extras `POPPING_EXTRAS`), then the paper's ops in one pass (ops 1
        to 4, 7 and 8), the holes removed with the pruning (the caps follow their rows). The noise
        of input Gaussian i is a pure function of (seed, op, i) in each.

        Args:
            cameras: the pair's cameras (a `Cameras` or a list): needed by depth, view_color,
                needles, floaters, shatter, popping, haze and veil.
            train_cameras: the virtual training cameras themselves (e.g. the views a real sparse
                fit of this scene was trained on, as calibrate passes them), of one size,
                instead of every `train_every`-th of `cameras`.

        Returns the scene, or (scene, keep-mask) with return_mask=True (the mask has a row per
        input Gaussian and, after them, per floater, fragment and haze Gaussian).

        Raises:
            ValueError: a sparse-view op that needs cameras without them (names the ops).
        """
        from morphgs._core import _perturb
        from morphgs.perturb import check_seed

        if not isinstance(scene, GaussianScene):
            raise TypeError(f"scene must be a GaussianScene, got {type(scene).__name__}")
        v = self.values()
        seed = check_seed(seed)
        keep = None
        if any(k in v for k in SPARSE_OPS):
            if self.needs_cameras and cameras is None and train_cameras is None:
                raise ValueError(f"the sparse-view op(s) {', '.join(k for k in CAMERA_OPS if k in v)} need the "
                                 "pair's cameras (cameras=...)")
            # the veil is drawn from the clean scene's training views, whatever the other ops do
            veil = self._veil(scene, v["veil"], seed, cameras, train_cameras) if v.get("veil", 0.0) > 0.0 else None
            if any(k in v for k in (*ARTIFACT_OPS, "shatter")):
                scene, keep = self._sparse_ops(scene, v, seed, cameras, train_cameras)
            if v.get("haze", 0.0) > 0.0:
                scene, keep = self._haze(scene, keep, v["haze"], seed, cameras, train_cameras)
            if veil is not None:
                scene, keep = _append(scene, keep, veil)
            if v.get("popping", 0.0) > 0.0:
                scene = self._popping(scene, v["popping"], seed, cameras, train_cameras)
        result: Any = _perturb(
            scene, position_jitter=v.get("position"), color_noise=v.get("color"),
            opacity_noise=v.get("opacity"), prune=1.0 - v["keep"] if "keep" in v else None,
            scale_noise=None, rotation_noise=None, log_scale_noise=v.get("log_scale"),
            rotation_angle=v.get("rotation"), seed=seed, return_mask=return_mask, keep=keep)
        return result

    def _haze(self, scene: GaussianScene, keep: Any, value: float, seed: int, cameras: Any,
              train_cameras: Any = None) -> tuple[GaussianScene, Any]:
        """`scene` with the haze Gaussians (`morphgs.haze`) appended, and `keep` (None: keep
        all) with a True row for each."""
        from morphgs.haze import haze_gaussians

        # its distances are in units of the training cameras' spacing
        train = self._two_views("haze", cameras, train_cameras)
        return _append(scene, keep, haze_gaussians(value, train.world_to_camera, train.K, int(train.width),
                                                   int(train.height), seed))

    def _two_views(self, op: str, cameras: Any, train_cameras: Any) -> Any:
        """The virtual training cameras of `op`, which needs two at least (else one line saying
        where they came from and the fix)."""
        train = self._train_views(cameras, train_cameras)
        if len(train) < 2:
            given = ("the given train_cameras" if train_cameras is not None
                     else f"every {self.train_every}th of the pair's {len(cameras)} cameras")
            raise ValueError(f"{op} needs at least 2 virtual training cameras, got {len(train)} ({given}): "
                             "use a longer path or a smaller train_every")
        return train

    def _veil(self, scene: GaussianScene, value: float, seed: int, cameras: Any,
              train_cameras: Any = None) -> dict[str, np.ndarray]:
        """The veil Gaussians (`morphgs.veil`) of the clean `scene`'s training views."""
        from morphgs.rendering import render
        from morphgs.veil import veil_gaussians

        train = self._two_views("veil", cameras, train_cameras)  # a veil Gaussian must agree with two
        clean = render(scene, train)
        h, w = int(train.height), int(train.width)
        return veil_gaussians(value, train.world_to_camera, train.K,
                              np.asarray(clean.rgb, np.float32).reshape(len(train), h, w, 3),
                              np.asarray(clean.depth, np.float32).reshape(len(train), h, w), seed)

    def _popping(self, scene: GaussianScene, fraction: float, seed: int, cameras: Any,
                 train_cameras: Any = None) -> GaussianScene:
        from morphgs._core import _popping

        train = self._train_views(cameras, train_cameras)
        return _popping(scene, popping=fraction, seed=seed,
                        world_to_camera=np.ascontiguousarray(train.world_to_camera, np.float64),
                        K=np.ascontiguousarray(train.K, np.float64), width=int(train.width), height=int(train.height))

    def _sparse_ops(self, scene: GaussianScene, v: Mapping[str, float], seed: int, cameras: Any,
                    train_cameras: Any = None) -> Any:
        if cameras is not None or train_cameras is not None:
            train = self._train_views(cameras, train_cameras)
            cameras = train
            w2c, K = train.world_to_camera, train.K
            width, height = train.width, train.height
        else:  # holes and dilate only
            w2c, K, width, height = np.zeros((0, 4, 4)), np.zeros((0, 3, 3)), 1, 1
        images = depth = None
        if cameras is not None:  # what each training view sees, and the floaters' colours
            from morphgs.rendering import render

            clean = render(scene, train)
            images = np.ascontiguousarray(np.asarray(clean.rgb, np.float32).reshape(len(train), height, width, 3))
            depth = np.ascontiguousarray(np.asarray(clean.depth, np.float32).reshape(len(train), height, width))
        if "shatter" in v:
            assert images is not None and depth is not None  # shatter is a camera op
            return self._shatter(self._artifacts(scene, v, seed, w2c, K, width, height, images, depth), v["shatter"],
                                 images, depth, np.asarray(clean.alpha, np.float32).reshape(len(train), height, width),
                                 w2c, K, seed)
        return self._artifacts(scene, v, seed, w2c, K, width, height, images, depth)

    @staticmethod
    def _shatter(done: Any, value: float, images: np.ndarray, depth: np.ndarray, alpha: np.ndarray, w2c: np.ndarray,
                 K: np.ndarray, seed: int) -> Any:
        """The shatter op (`morphgs.shatter`) on the other sparse-view ops' (scene, keep): the
        removed Gaussians dropped from keep, the fragments appended (kept)."""
        from morphgs import shatter

        scene, keep = done
        n = len(scene)
        keep = np.ones(n, bool) if keep is None else np.asarray(keep, bool)
        gone = shatter.removal(n, value, seed)
        frag = shatter.fragments(value, images, depth, alpha, w2c, K, int(np.sum(gone & keep)), seed)
        m = len(frag["means"])
        sh_rest = np.asarray(scene.sh_rest, np.float32)
        if sh_rest.shape[1] == 0:  # degree 0: the fragments' view-dependent colour needs band 1
            sh_rest = np.zeros((n, 3, 3), np.float32)
        rest = np.zeros((m, *sh_rest.shape[1:]), np.float32)
        rest[:, :3, :] = frag["sh1"]
        extras = {k: np.concatenate([a, np.zeros((m, *a.shape[1:]), a.dtype)]) for k, a in scene.extras.items()}
        joined = GaussianScene.from_arrays(
            means=np.concatenate([scene.means, frag["means"]]), quats=np.concatenate([scene.quats, frag["quats"]]),
            log_scales=np.concatenate([scene.log_scales, frag["log_scales"]]),
            opacity_logits=np.concatenate([scene.opacity_logits, frag["opacity_logits"]]),
            sh0=np.concatenate([scene.sh0, frag["sh0"]]), sh_rest=np.concatenate([sh_rest, rest]),
            extras=extras or None)
        return joined, np.ascontiguousarray(np.concatenate([keep & ~gone, np.ones(m, bool)]))

    @staticmethod
    def _artifacts(scene: GaussianScene, v: Mapping[str, float], seed: int, w2c: Any, K: Any, width: int, height: int,
                   images: Any, depth: Any) -> Any:
        from morphgs._core import _artifacts

        return _artifacts(scene, depth=v.get("depth"), view_color=v.get("view_color"), needles=v.get("needles"),
                          holes=v.get("holes"), hole_size=0.05, dilate=v.get("dilate"), floaters=v.get("floaters"),
                          world_to_camera=np.ascontiguousarray(w2c, np.float64), K=np.ascontiguousarray(K, np.float64),
                          width=int(width), height=int(height), images=images, depth_maps=depth, seed=seed)


def _append(scene: GaussianScene, keep: Any, h: Mapping[str, np.ndarray]) -> tuple[GaussianScene, Any]:
    """`scene` with the rows `h` (an appending op's: means, quats, log_scales, opacity_logits, sh0;
    higher SH bands and extras zero) after its own, and `keep` (None: keep all) with a True row for
    each."""
    m = len(h["means"])
    if m == 0:
        return scene, keep
    sh_rest = np.asarray(scene.sh_rest, np.float32)
    extras = {k: np.concatenate([a, np.zeros((m, *a.shape[1:]), a.dtype)]) for k, a in scene.extras.items()}
    joined = GaussianScene.from_arrays(
        means=np.concatenate([scene.means, h["means"]]), quats=np.concatenate([scene.quats, h["quats"]]),
        log_scales=np.concatenate([scene.log_scales, h["log_scales"]]),
        opacity_logits=np.concatenate([scene.opacity_logits, h["opacity_logits"]]),
        sh0=np.concatenate([scene.sh0, h["sh0"]]),
        sh_rest=np.concatenate([sh_rest, np.zeros((m, *sh_rest.shape[1:]), np.float32)]),
        extras=extras or None)
    if keep is not None:
        keep = np.ascontiguousarray(np.concatenate([np.asarray(keep, bool), np.ones(m, bool)]))
    return joined, keep


#: The largest blur sigma (pixels) of `Blur2d` (as curate's blur2d).
BLUR_MAX_SIGMA = 256.0


@dataclasses.dataclass(frozen=True)
class Blur2d:
    """The paper's 2D baseline (image-space render blur) as a strength family: at strength s the
    corrupted frames are the clean frames blurred by a Gaussian of sigma = s pixels (s = 0 is the
    identity). It has one op, "sigma", of base value 1, so the strength is the sigma itself; it
    acts on rendered frames, not on the scene (`blur`).

    Raises:
        ValueError: a strength that is not finite, negative or above `BLUR_MAX_SIGMA`.
    """

    strength: float = 1.0

    def __post_init__(self) -> None:
        v = _number(self.strength, "strength")
        if v > BLUR_MAX_SIGMA:
            raise ValueError(f"a blur2d strength is a sigma in pixels in [0, {BLUR_MAX_SIGMA:g}], got {v!r}")
        object.__setattr__(self, "strength", v)

    family = "blur2d"

    @property
    def base(self) -> dict[str, float]:
        """The one op and its base value (the sigma at strength 1)."""
        return {"sigma": 1.0}

    def at(self, strength: float) -> Blur2d:
        return Blur2d(strength)

    def only(self, op: str) -> Blur2d:
        if op != "sigma":
            raise ValueError(f"op {op!r} is not enabled in this config (sigma)")
        return self

    def values(self) -> dict[str, float]:
        return {"sigma": self.strength}

    def to_dict(self) -> dict[str, Any]:
        """{"kind": "blur2d", "sigma"} (what curate's blur2d config takes)."""
        return {"kind": "blur2d", "sigma": self.strength}

    def blur(self, rgb: np.ndarray) -> np.ndarray:
        """Frames (F, H, W, 3) float32 blurred by sigma = strength pixels (curate's blur2d)."""
        from morphgs._core import gaussian_blur

        return gaussian_blur(np.ascontiguousarray(rgb, dtype=np.float32), self.strength)


#: Op id of a pair's strength draw from a strength distribution (`draw_strength`).
OP_STRENGTH_DRAW = noise.OP_STRENGTH_DRAW


def check_quantiles(table: Any, where: str = "quantiles") -> tuple[list[float], list[float]]:
    """Validate a strength quantile table {"p": [...], "strength": [...]}.

    p must rise strictly from 0 to 1 and the strengths must be finite, >= 0 and non-decreasing.

    Raises:
        ValueError: naming `where` and the problem.
    """
    if not isinstance(table, Mapping) or set(table) != {"p", "strength"}:
        raise ValueError(f"{where} must be an object {{\"p\": [...], \"strength\": [...]}}")
    p, s = table["p"], table["strength"]
    if not (isinstance(p, list) and isinstance(s, list)) or len(p) != len(s) or len(p) < 2:
        raise ValueError(f"{where}: 'p' and 'strength' must be lists of the same length >= 2")
    try:
        pf = [float(x) for x in p]
        sf = [_number(x, f"{where}.strength") for x in s]
    except TypeError as e:
        raise ValueError(f"{where}: {e}") from None
    if pf[0] != 0.0 or pf[-1] != 1.0 or any(b <= a for a, b in zip(pf, pf[1:])):
        raise ValueError(f"{where}.p must rise strictly from 0 to 1, got {p}")
    if any(b < a for a, b in zip(sf, sf[1:])):
        raise ValueError(f"{where}.strength must be non-decreasing, got {s}")
    return pf, sf


def draw_strength(config: Mapping[str, Any], seed: int) -> float:
    """The strength a pair of pair seed `seed` uses under a strength config.

    A fixed "strength" is returned as is; a "quantiles" table {"p", "strength"} (the inverse CDF
    of a strength distribution, linear between its points) is sampled at u, the uniform of index
    0 in op `OP_STRENGTH_DRAW` of the seed's stream: a pure function of the seed.
    """
    if "quantiles" not in config:
        return _number(config.get("strength", 1.0), "strength")
    p, s = check_quantiles(config["quantiles"])
    u = float(noise.uniforms(int(seed), OP_STRENGTH_DRAW, [0])[0])
    return float(np.interp(u, p, s))


def from_config(config: Mapping[str, Any], seed: int) -> Strength:
    """The `Strength` of one pair: `config` with its strength drawn (see `draw_strength`)."""
    fixed = {k: v for k, v in config.items() if k != "quantiles"}
    fixed["strength"] = draw_strength(config, seed)
    return Strength.from_dict(fixed)
