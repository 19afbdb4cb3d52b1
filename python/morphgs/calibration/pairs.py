"""Real pairs (read from a curated folder) and their synthetic counterparts (rendered on the same
cameras with the same seeds at any strength)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import MorphgsError
from morphgs.camera import Cameras

__all__ = ["Bench", "CalibrationError", "RealPair", "by_regime", "read_real_pairs"]


class CalibrationError(MorphgsError):
    """Bad calibration input (the message names the file or option and the problem)."""


@dataclass(frozen=True)
class RealPair:
    """One real pair: frames (F, H, W, 3) float32 in [0, 1], its cameras, scene and seed."""

    pair_id: str
    scene: str
    regime: str
    seed: int
    cameras: Cameras
    corrupted: np.ndarray
    clean: np.ndarray
    #: the real fit's training cameras at the pair's size, when the pair records its fit (a
    #: `sparse:K` pair): the sparse-view ops' virtual training cameras are then those very views
    train_cameras: Cameras | None = None


def _read_frames(path: Path, what: str) -> np.ndarray:
    from morphgs.media import read_clip

    if not path.exists():
        raise CalibrationError(f"{path}: the pair's {what} frames are missing")
    return np.asarray(read_clip(path), dtype=np.float32) / np.float32(255.0)


def _fit_train_cameras(root: Path, fit: Any, width: int, height: int) -> Cameras | None:
    """The training cameras of a pair's real fit (the fit's data/transforms.json: its first
    len(train_views) frames, as `curation.sparse` writes it), resized to the pair's size; None when
    the pair records no fit or its data has gone."""
    from morphgs.trajectory import read_transforms_frames, resize_camera

    if not isinstance(fit, dict) or "dir" not in fit or not isinstance(fit.get("train_views"), list):
        return None
    path = root / str(fit["dir"]) / "data" / "transforms.json"
    if not path.is_file():
        return None
    try:
        frames = read_transforms_frames(path, sort=False)
    except (OSError, ValueError, MorphgsError) as e:
        raise CalibrationError(f"{path}: cannot read the real fit's training cameras ({e})") from None
    n = len(fit["train_views"])
    if len(frames) < n:
        raise CalibrationError(f"{path}: {len(frames)} frames for the fit's {n} training views (field 'frames')")
    return Cameras.from_list([resize_camera(f.camera, width, height) for f in frames[:n]])


def read_real_pairs(folder: str | os.PathLike[str], *, regimes: Sequence[str] | None = None) -> list[RealPair]:
    """The pairs of a curated folder (its manifest*.jsonl), sorted by pair id.

    Any pair whose corrupted side is real counts, e.g. `sparse:K` pairs or the user's own
    reconstructions curated with a JSON config. `regimes` keeps only these config names.

    Raises:
        CalibrationError: no manifest or no pairs (naming the folder), a pair whose clean and
            corrupted frames (or its cameras) differ in size or count (naming the pair and field).
    """
    from morphgs.curation import load_manifest

    root = Path(folder)
    if not root.is_dir():
        raise CalibrationError(f"--real {root}: not a folder")
    records = load_manifest(root)
    if regimes is not None:
        records = {k: r for k, r in records.items() if r.get("config_name") in set(regimes)}
    if not records:
        what = f" for {', '.join(regimes)}" if regimes is not None else ""
        raise CalibrationError(f"--real {root}: no pairs{what} (expected manifest*.jsonl lines as morphgs curate "
                               "writes, with clean/ and corrupted/ frames)")
    out = []
    for pid in sorted(records):
        r = records[pid]
        paths = r.get("paths", {})
        try:
            cams = Cameras.from_dict(json.loads((root / paths["cameras"]).read_text(encoding="utf-8")))
        except (KeyError, OSError, ValueError) as e:
            raise CalibrationError(f"{root / paths.get('cameras', pid)}: cannot read the pair's cameras ({e})") from None
        corrupted = _read_frames(root / paths.get("corrupted", f"pairs/{pid}/corrupted"), "corrupted")
        clean = _read_frames(root / paths.get("clean", f"pairs/{pid}/clean"), "clean")
        if corrupted.shape != clean.shape:
            raise CalibrationError(f"{root / r['paths']['dir']}: corrupted frames {corrupted.shape[1:3]} x "
                                   f"{len(corrupted)} and clean frames {clean.shape[1:3]} x {len(clean)} differ "
                                   "(field 'paths.corrupted' vs 'paths.clean')")
        if len(cams) != len(clean) or (cams[0].height, cams[0].width) != clean.shape[1:3]:
            raise CalibrationError(f"{root / paths['cameras']}: {len(cams)} cameras of {cams[0].width}x"
                                   f"{cams[0].height} for {len(clean)} frames of {clean.shape[2]}x{clean.shape[1]}")
        out.append(RealPair(pid, str(r["scene"]), str(r.get("config_name", "real")), int(r["seed"]), cams,
                            corrupted, clean, _fit_train_cameras(root, r.get("fit"), cams[0].width, cams[0].height)))
    sizes = {p.clean.shape[1:3] for p in out}
    if len(sizes) > 1:
        raise CalibrationError(f"--real {root}: pairs of mismatched sizes {sorted(sizes)} (field 'resolution'); "
                               "calibrate one size at a time")
    return out


def by_regime(pairs: Sequence[RealPair]) -> dict[str, list[RealPair]]:
    """The pairs grouped by regime (their config name), regimes and pairs in the order given."""
    out: dict[str, list[RealPair]] = {}
    for p in pairs:
        out.setdefault(p.regime, []).append(p)
    return out


def _add(seconds: dict[str, float] | None, **kw: float) -> None:
    if seconds is not None:
        for k, v in kw.items():
            seconds[k] = seconds.get(k, 0.0) + v


def _quantise(rgb: np.ndarray) -> np.ndarray:
    """Frames as a curated folder stores them: round(clip(rgb, 0, 1) * 255) / 255, so synthetic and
    real pairs are compared at the same precision."""
    return np.rint(np.clip(rgb, 0.0, 1.0) * np.float32(255.0)).astype(np.float32) / np.float32(255.0)


class Bench:
    """Synthetic pairs on the real pairs' cameras and seeds (common random numbers).

    Args:
        scenes: scene id -> clean GaussianScene, for every pair's scene.
        pairs: the real pairs.
    """

    def __init__(self, scenes: Mapping[str, Any], pairs: Sequence[RealPair]) -> None:
        from morphgs.rendering import render_many

        missing = sorted({p.scene for p in pairs} - set(scenes))
        if missing:
            raise CalibrationError(f"the real pairs' scene(s) {', '.join(missing)} are not among the SCENES given")
        self.scenes, self.pairs = scenes, list(pairs)
        self._rgb = [render_many([scenes[p.scene]], p.cameras)[0].rgb for p in self.pairs]
        self.clean = [_quantise(rgb) for rgb in self._rgb]

    def corrupted(self, config: Any, index: int, seconds: dict[str, float] | None = None) -> np.ndarray:
        """The synthetic corrupted frames of pair `index` under a `Strength` config (popping
        included: the render honours the scene's caps frame by frame), or a `Blur2d` one (the
        clean render blurred, as curate's blur2d). `seconds`, when given, gains the wall seconds
        spent: "perturb" (for blur2d, the blur) and "render"."""
        from morphgs.rendering import render_many
        from morphgs.strength import Blur2d

        t0 = time.perf_counter()
        if isinstance(config, Blur2d):
            out = _quantise(config.blur(self._rgb[index]))
            _add(seconds, perturb=time.perf_counter() - t0)
            return out
        p = self.pairs[index]
        scene = config.apply(self.scenes[p.scene], seed=p.seed, cameras=p.cameras, train_cameras=p.train_cameras)
        t1 = time.perf_counter()
        _add(seconds, perturb=t1 - t0)
        if len(scene) == 0:
            return np.zeros_like(self.clean[index])
        out = _quantise(render_many([scene], p.cameras)[0].rgb)
        _add(seconds, render=time.perf_counter() - t1)
        return out

    def frame_psnr(self, config: Any) -> np.ndarray:
        """Per-frame PSNR of every synthetic pair under `config`, concatenated in pair order."""
        from morphgs.calibration.stats import frame_psnr

        return np.concatenate([frame_psnr(self.corrupted(config, i), c) for i, c in enumerate(self.clean)])

    def frame_mse(self, config: Any) -> float:
        """Mean squared error over every synthetic frame under `config`."""
        return float(np.mean([np.mean((self.corrupted(config, i).astype(np.float64) - c) ** 2)
                              for i, c in enumerate(self.clean)]))
