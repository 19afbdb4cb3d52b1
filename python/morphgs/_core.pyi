# Hand-written stubs for the native module; checked with `python -m mypy.stubtest morphgs._core`.
from collections.abc import Mapping, Sequence
from os import PathLike
from typing import Any, Literal, final

import numpy as np
import numpy.typing as npt

__version__: str

_F32 = npt.NDArray[np.float32]
_Path = str | PathLike[str]

# ---- errors ----
class MorphgsError(ValueError): ...

class SceneFormatError(MorphgsError):
    path: str
    element: str | None
    property: str | None

class MorphgsWarning(UserWarning): ...

# ---- scene ----
@final
class GaussianScene:
    @staticmethod
    def from_arrays(
        *,
        means: npt.ArrayLike,
        quats: npt.ArrayLike,
        log_scales: npt.ArrayLike,
        opacity_logits: npt.ArrayLike,
        sh0: npt.ArrayLike,
        sh_rest: npt.ArrayLike | None = None,
        extras: Mapping[str, npt.ArrayLike] | None = None,
    ) -> GaussianScene: ...
    @property
    def means(self) -> _F32: ...
    @property
    def quats(self) -> _F32: ...
    @property
    def log_scales(self) -> _F32: ...
    @property
    def opacity_logits(self) -> _F32: ...
    @property
    def sh0(self) -> _F32: ...
    @property
    def sh_rest(self) -> _F32: ...
    @property
    def sh_degree(self) -> int: ...
    @property
    def extras(self) -> dict[str, _F32]: ...
    @property
    def scales(self) -> _F32: ...
    @property
    def opacities(self) -> _F32: ...
    @property
    def colors(self) -> _F32: ...
    def bounds(self) -> tuple[_F32, _F32]: ...
    def subset(self, indices_or_mask: npt.ArrayLike) -> GaussianScene: ...
    def __len__(self) -> int: ...
    def __reduce__(self) -> tuple[Any, tuple[dict[str, Any]]]: ...

def _scene_from_state(state: dict[str, Any]) -> GaussianScene: ...

# ---- io ----
def load(
    path: _Path,
    *,
    on_invalid: Literal["error", "drop"] | str = "error",
    spz_axes: Literal["rdf", "stored"] | str = "rdf",
) -> GaussianScene: ...
def save_ply(scene: GaussianScene, path: _Path) -> None: ...
def num_threads() -> int: ...

# ---- render ----
_U8 = npt.NDArray[np.uint8]

def _render(
    scenes: list[GaussianScene],
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    background: tuple[float, float, float] | list[float] = ...,
    max_alpha: float = 0.99,
    sh_degree: int | None = None,
    antialiased: bool = False,
    out: tuple[_F32, _F32, _F32] | None = None,
) -> tuple[_F32, _F32, _F32, dict[str, Any]]: ...
def _project(
    scene: GaussianScene,
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    sh_degree: int | None = None,
    antialiased: bool = False,
) -> dict[str, npt.NDArray[Any]]: ...
def _write_png(path: _Path, image: _U8 | _F32) -> None: ...
def _write_exr(path: _Path, image: _F32) -> None: ...
def _write_png_batch(paths: Sequence[_Path], images: _U8 | _F32, batched: bool = True) -> None: ...
def _write_exr_batch(paths: Sequence[_Path], images: _F32, batched: bool = True) -> None: ...
def _read_exr_batch(paths: Sequence[_Path], max_values: int = ...) -> list[_F32]: ...
def _read_png_batch(
    paths: Sequence[_Path], max_rows: int | None = None, max_values: int = ...
) -> list[tuple[_U8, int]]: ...
# ---- differentiable rasterizer ----
@final
class DiffRasterizer:
    def __init__(self) -> None: ...
    def forward(
        self,
        means: _F32,
        quats: _F32,
        log_scales: _F32,
        opacity_logits: _F32,
        sh0: _F32,
        sh_rest: _F32,
        world_to_camera: npt.NDArray[np.float64],
        K: npt.NDArray[np.float64],
        width: int,
        height: int,
        *,
        near: float = 0.01,
        far: float = 1e10,
        background: tuple[float, float, float] | list[float] = ...,
        max_alpha: float = 0.99,
        sh_degree: int | None = None,
        antialiased: bool = False,
        colors: _F32 | None = None,
        depth: Literal["expected", "accumulated"] = "expected",
        slot_budget: int = ...,
        absgrad: bool = False,
    ) -> tuple[_F32, _F32, _F32, dict[str, Any]]: ...
    def backward(
        self,
        means: _F32,
        quats: _F32,
        log_scales: _F32,
        opacity_logits: _F32,
        sh0: _F32,
        sh_rest: _F32,
        *,
        colors: _F32 | None = None,
        v_rgb: _F32 | None = None,
        v_depth: _F32 | None = None,
        v_alpha: _F32 | None = None,
        view: bool = False,
        viewmat: bool = False,
        cameras_per_step: float = 1.0,
    ) -> dict[str, Any]: ...
    def projection(self) -> dict[str, npt.NDArray[Any]]: ...
    def contributions(
        self,
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.bool_]]: ...

# ---- formats (.splat, .spz) ----
def save_splat(scene: GaussianScene, path: _Path) -> None: ...
def save_spz(
    scene: GaussianScene,
    path: _Path,
    *,
    spz_axes: Literal["rdf", "stored"] | str = "rdf",
    version: int = 3,
) -> None: ...
def save_compressed_ply(scene: GaussianScene, path: _Path) -> None: ...
def save_glb(scene: GaussianScene, path: _Path) -> None: ...

# ---- blur (curate / blur2d baseline) ----
def gaussian_blur(images: npt.NDArray[np.float32], sigma: float) -> _F32: ...

# ---- perturb ----
def _perturb(
    scene: GaussianScene,
    *,
    position_jitter: float | None,
    color_noise: float | None,
    opacity_noise: float | None,
    prune: float | None,
    scale_noise: float | None,
    rotation_noise: float | None,
    seed: int,
    return_mask: bool = False,
    log_scale_noise: float | None = None,
    rotation_angle: float | None = None,
    keep: npt.NDArray[np.bool_] | None = None,
) -> GaussianScene | tuple[GaussianScene, npt.NDArray[np.bool_]]: ...
def _artifacts(
    scene: GaussianScene,
    *,
    depth: float | None,
    view_color: float | None,
    needles: float | None,
    holes: float | None,
    hole_size: float,
    dilate: float | None,
    floaters: float | None,
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    width: int,
    height: int,
    images: npt.NDArray[np.float32] | None,
    depth_maps: npt.NDArray[np.float32] | None,
    seed: int,
) -> tuple[GaussianScene, npt.NDArray[np.bool_]]: ...
def _popping(
    scene: GaussianScene,
    *,
    popping: float,
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    width: int,
    height: int,
    seed: int,
) -> GaussianScene: ...
def _haze(
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    width: int,
    height: int,
    *,
    value: float,
    seed: int,
) -> dict[str, npt.NDArray[np.float32]]: ...
def _veil(
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    images: npt.NDArray[np.float32],
    depth: npt.NDArray[np.float32],
    *,
    value: float,
    seed: int,
) -> dict[str, npt.NDArray[np.float32]]: ...
def _shatter_removal(n: int, *, value: float, seed: int) -> npt.NDArray[np.bool_]: ...
def _shatter(
    value: float,
    images: npt.NDArray[np.float32],
    depth: npt.NDArray[np.float32],
    alpha: npt.NDArray[np.float32],
    world_to_camera: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    removed: int,
    *,
    seed: int,
    ridge: float = 1.0,
    max_error: float = 0.08,
    drop: bool = True,
) -> dict[str, npt.NDArray[Any]]: ...

# ---- fit (morphgs.fit) ----
_FitCallback = Any  # (kind: str, payload: Any) -> Any

@final
class Trainer:
    def __new__(
        cls,
        scene: GaussianScene,
        images: list[npt.NDArray[np.uint8]],
        world_to_camera: npt.NDArray[np.float64],
        K: npt.NDArray[np.float64],
        *,
        config: dict[str, Any],
        eval_images: list[npt.NDArray[np.uint8]] | None = None,
        eval_world_to_camera: npt.NDArray[np.float64] | None = None,
        eval_K: npt.NDArray[np.float64] | None = None,
        masks: list[npt.NDArray[np.uint8] | None] | None = None,
        eval_masks: list[npt.NDArray[np.uint8] | None] | None = None,
    ) -> Trainer: ...
    @staticmethod
    def restore(
        path: _Path,
        images: list[npt.NDArray[np.uint8]],
        world_to_camera: npt.NDArray[np.float64],
        K: npt.NDArray[np.float64],
        *,
        config: dict[str, Any],
        fingerprint: bytes,
        eval_images: list[npt.NDArray[np.uint8]] | None = None,
        eval_world_to_camera: npt.NDArray[np.float64] | None = None,
        eval_K: npt.NDArray[np.float64] | None = None,
        masks: list[npt.NDArray[np.uint8] | None] | None = None,
        eval_masks: list[npt.NDArray[np.uint8] | None] | None = None,
    ) -> Trainer: ...
    @property
    def step(self) -> int: ...
    def __len__(self) -> int: ...
    def scene(self) -> GaussianScene: ...
    def view_at(self, step: int) -> int: ...
    def run(
        self,
        until: int,
        *,
        callback: _FitCallback | None = None,
        eval_every: int = 0,
        checkpoint: _Path | None = None,
        checkpoint_every: int = 0,
        fingerprint: bytes | None = None,
        progress_every: float = 0.5,
    ) -> str: ...
    def save_checkpoint(self, path: _Path, *, fingerprint: bytes | None = None) -> None: ...
    def evaluate(self) -> list[tuple[float, float]]: ...
    def render(
        self, world_to_camera: npt.NDArray[np.float64], K: npt.NDArray[np.float64], width: int, height: int
    ) -> _F32: ...

def _fit_init_scene(
    points: _F32, colors: _F32, *, opacity: float, scale: float, sh_degree: int
) -> GaussianScene: ...
def _fit_random_points(
    n: int, lo: Sequence[float], hi: Sequence[float], *, seed: int
) -> tuple[_F32, _F32]: ...
def _fit_loss(render: _F32, target: _F32, *, ssim_lambda: float = 0.2) -> tuple[float, float, float, _F32]: ...
def _ssim_batch(pred: npt.NDArray[np.float32], target: npt.NDArray[np.float32], *,
                grad: bool = True) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32] | None]: ...
