"""`morphgs.fit.fit(...)`: posed images in, a trained 3DGS scene and a run folder out.

The run folder (docs/fit.md, "Run folder"):

    config.toml                       the config as used (every value)
    views.json                        training and held-out views (indices and file names)
    cameras.json                      every view's camera, INRIA 3DGS layout
    loss.csv                          per step: loss, L1, SSIM, train PSNR, Gaussians, ...
    eval.csv, eval_views.csv          held-out PSNR / SSIM / LPIPS (mean; per view) every eval_every steps
    previews/step_NNNNNN.png          first held-out view: render | ground truth
    checkpoint.bin                    the state to resume from (atomic, with a checksum)
    checkpoint.prev.bin               the one before it (a hard link), used when checkpoint.bin is damaged
    point_cloud/iteration_N/point_cloud.ply   the result, INRIA PLY layout
    fit.json                          summary (written last: its presence means done)

The loop runs natively in one call; the CSV rows arrive through its callback in batches and are
flushed before every checkpoint, so after a kill (even SIGKILL) a rerun resumes from the last
checkpoint, drops the rows logged after it and continues bit for bit: the same scene, the same
rows.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import os
import shutil
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from morphgs._core import GaussianScene, MorphgsError, MorphgsWarning
from morphgs.camera import Camera
from morphgs.fit.config import FitConfig
from morphgs.fit.data import PosedImages, describe, load_posed_images
from morphgs.fit.views import ViewSelection, select_views
from morphgs.reliability import folder_lock, signals_held

__all__ = ["FitPastError", "FitResult", "FitRunError", "fit", "random_init_on_purpose", "scene_scale_of"]

LOSS_COLUMNS = ["step", "view", "loss", "l1", "ssim", "psnr", "gaussians", "sh_degree", "lr_means",
                "duplicated", "split", "pruned", "reset", "relocated", "added", "seconds"]
EVAL_COLUMNS = ["step", "psnr", "ssim", "lpips"]
EVAL_VIEW_COLUMNS = ["step", "view", "name", "psnr", "ssim", "lpips"]


class FitRunError(MorphgsError):
    """A run folder that holds another run (other config or data) than the one asked for."""


class FitPastError(FitRunError):
    """`fit(..., until=S)` on a run folder whose run is already past step S."""


@dataclass
class FitResult:
    """What a fit produced.

    Attributes:
        run_dir: the run folder; ply: the result's PLY; scene: the trained GaussianScene.
        steps: steps done; train_views, heldout_views: view indices of the dataset.
        heldout_psnr, heldout_ssim, heldout_lpips: mean held-out metrics of the result (None
            without held-out views; LPIPS None when it is off or unavailable); gaussians: the result's size; seconds: wall time of this call;
        steps_per_second: steps of this call per second (None when nothing was left to do).
    """

    run_dir: Path
    ply: Path
    scene: GaussianScene
    steps: int
    train_views: list[int]
    heldout_views: list[int]
    heldout_psnr: float | None
    heldout_ssim: float | None
    gaussians: int
    seconds: float
    steps_per_second: float | None
    summary: dict[str, Any] = field(default_factory=dict, repr=False)
    heldout_lpips: float | None = None


def scene_scale_of(cameras: Sequence[Camera]) -> float:
    """INRIA's cameras_extent / gsplat's scene_scale: 1.1 x the largest distance of a camera
    centre from their mean (1.0 when the cameras coincide, e.g. one view)."""
    c = np.stack([cam.center for cam in cameras]) if len(cameras) else np.zeros((1, 3))
    r = float(np.linalg.norm(c - c.mean(axis=0), axis=1).max()) * 1.1
    return r if r > 1e-6 else 1.0


def _resolve_config(config: Any) -> FitConfig:
    if config is None:
        return FitConfig()
    if isinstance(config, FitConfig):
        return config
    if isinstance(config, dict):
        return FitConfig.from_dict(config)
    if isinstance(config, str) and config in ("default", "mcmc", "sparse"):
        return FitConfig.preset(config)
    return FitConfig.load(config)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _truncate_csv(path: Path, step: int, columns: list[str]) -> None:
    """Keep the header and the rows of steps <= `step` (a fresh file when there is none)."""
    rows: list[str] = []
    if path.is_file():
        lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
        for line in lines[1:]:
            if not line.endswith("\n"):
                break  # cut short by a kill
            try:
                if int(line.split(",", 1)[0]) <= step:
                    rows.append(line)
            except ValueError:
                continue
    _write_atomic(path, ",".join(columns) + "\n" + "".join(rows))


def _lpips_scorer(setting: str, images: list[np.ndarray], *, verbose: bool,
                  masks: Sequence[np.ndarray | None] = ()) -> Callable[[np.ndarray, int], float] | None:
    """A function (render, held-out view index) -> LPIPS against that view's image, or None.
    Masked pixels (`masks[view]` False) of the render are replaced by the image's own before
    scoring, so they cannot count.

    "auto" gives AlexNet when torch and the weights are installed and None (with a note) when
    not; "alex"/"vgg" must work (the error says what to install); "off" is None. The scorer runs
    in torch and never touches the fit, whose bytes do not depend on it.
    """
    if setting == "off" or not images:
        return None
    net = "alex" if setting == "auto" else setting
    try:
        from morphgs.metrics import lpips, lpips_model
        from morphgs.metrics.perceptual import lpips_min_size

        h, w = images[0].shape[:2]
        if min(h, w) < lpips_min_size(net):
            if setting == "auto":
                return None
            raise MorphgsError(f"output.lpips = {setting!r}: held-out images of {w}x{h} are smaller than LPIPS "
                               f"{net} accepts ({lpips_min_size(net)} pixels a side)")
        lpips_model(net)
    except (ImportError, MorphgsError) as e:
        if setting != "auto":
            raise
        if verbose:
            first = str(e).splitlines()[0] if str(e) else type(e).__name__
            print(f"held-out LPIPS off: {first} (output.lpips = 'off' silences this)", flush=True)
        return None

    import torch

    def score(rgb: np.ndarray, view: int) -> float:
        # one torch thread: the column then has the same bits whatever torch's default thread
        # count (the scene's bytes never depend on it)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        rgb = np.clip(rgb, 0.0, 1.0)
        m = masks[view] if view < len(masks) else None
        if m is not None:
            rgb = np.where(m[..., None], rgb, images[view].astype(np.float32) / 255.0)
        try:
            return float(lpips(rgb, images[view], net=net))
        finally:
            torch.set_num_threads(threads)

    return score


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _inria_cameras(cams: Sequence[Camera], names: list[str]) -> list[dict[str, Any]]:
    out = []
    for i, (c, n) in enumerate(zip(cams, names)):
        c2w = c.camera_to_world
        out.append({"id": i, "img_name": Path(n).stem, "width": c.width, "height": c.height,
                    "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
                    "fx": c.fx, "fy": c.fy})
    return out


def _preview(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    r = np.rint(np.clip(render, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.ascontiguousarray(np.concatenate([r, truth], axis=1))


def _stack(cams: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    w2c = np.ascontiguousarray(np.stack([c.world_to_camera for c in cams]), np.float64)
    k = np.ascontiguousarray(np.stack([c.K for c in cams]), np.float64)
    return w2c, k


class _Logger:
    """Receives the native loop's callbacks: CSV rows, previews, the progress bar."""

    def __init__(self, run: Path, cfg: FitConfig, heldout_names: list[str], heldout_images: list[np.ndarray],
                 bar: Any, user: Callable[[str, Any], Any] | None, verbose: bool,
                 lpips: Callable[[np.ndarray, int], float] | None = None) -> None:
        self.run, self.cfg, self.names, self.truth, self.bar, self.user = run, cfg, heldout_names, heldout_images, bar, user
        self.verbose = verbose
        self.lpips = lpips
        self.view_lpips: dict[int, float] = {}
        self.loss = open(run / "loss.csv", "a", encoding="utf-8", newline="")
        self.eval = open(run / "eval.csv", "a", encoding="utf-8", newline="")
        self.eval_views = open(run / "eval_views.csv", "a", encoding="utf-8", newline="")
        self.last: dict[str, Any] = {}
        self.last_eval: dict[str, Any] = {}
        self.written = 0  # the last step whose loss row is written (the file holds those before the start)

    def __call__(self, kind: str, payload: Any) -> Any:
        with signals_held():  # a Ctrl-C raises once this event's rows are all written
            payload = self._log(kind, payload)
        if self.user is not None:
            return self.user(kind, payload)
        return None

    def _log(self, kind: str, payload: Any) -> Any:
        if kind == "steps":
            # a batch comes again when a Ctrl-C landed in its call (Trainer.run): skip what is written
            payload = [r for r in payload if r["step"] > self.written]
            for r in payload:
                self.loss.write(",".join(_fmt(r[c]) for c in LOSS_COLUMNS) + "\n")
                self.written = r["step"]
                for what in ("duplicated", "split", "pruned", "relocated", "added"):
                    if r[what] and self.verbose:
                        self.bar.write(f"step {r['step']}: {r['duplicated']} duplicated, {r['split']} split, "
                                       f"{r['pruned']} pruned, {r['relocated']} relocated, {r['added']} added "
                                       f"-> {r['gaussians']} Gaussians")
                        break
                if r["reset"] and self.verbose:
                    self.bar.write(f"step {r['step']}: opacities reset")
            self.loss.flush()
            if payload:
                self.last = payload[-1]
                self.bar.set_postfix_str(
                    f"loss {self.last['loss']:.4f} psnr {self.last['psnr']:.2f} N {self.last['gaussians']}",
                    refresh=False)
                self.bar.update(len(payload))
        elif kind == "eval_view":
            step, v = payload["step"], payload["view"]
            lp = self.lpips(payload["rgb"], v) if self.lpips is not None else None
            if lp is not None:
                self.view_lpips[v] = lp
            self.eval_views.write(",".join(_fmt(x) for x in (step, v, self.names[v], payload["psnr"], payload["ssim"], lp))
                                  + "\n")
            pe = self.cfg.output.preview_every
            if v == 0 and (step == self.cfg.steps or (pe > 0 and step % pe == 0)):
                from morphgs._core import _write_png

                (self.run / "previews").mkdir(exist_ok=True)
                _write_png(self.run / "previews" / f"step_{step:06d}.png", _preview(payload["rgb"], self.truth[0]))
        elif kind == "eval":
            lp = float(np.mean(list(self.view_lpips.values()))) if self.view_lpips else None
            self.view_lpips = {}
            payload = dict(payload, lpips=lp)
            self.eval.write(",".join(_fmt(payload[c]) for c in EVAL_COLUMNS) + "\n")
            self.eval.flush()
            self.eval_views.flush()
            self.last_eval = payload
            if self.verbose:
                self.bar.write(f"step {payload['step']}: held-out PSNR {payload['psnr']:.3f} dB, SSIM {payload['ssim']:.4f}"
                               + (f", LPIPS {lp:.4f}" if lp is not None else ""))
        elif kind == "checkpoint":
            _keep_previous(self.run / "checkpoint.bin")
        return payload

    def close(self) -> None:
        for f in (self.loss, self.eval, self.eval_views):
            f.close()


def _warn_forward_facing(init: Any, posed: PosedImages, cams: Sequence[Camera]) -> None:
    """A MorphgsWarning when a forward-facing capture is fitted from random points."""
    import warnings

    from morphgs._core import MorphgsWarning
    from morphgs.fit.rays import looks_forward_facing

    spec = init.strip() if isinstance(init, str) else ""
    random = spec.startswith(("random", "box")) or (spec == "auto" and posed.points is None)
    if random and looks_forward_facing(cams):
        warnings.warn(f"{posed.source}: the capture looks forward-facing (every camera looks within 30 degrees of "
                      "one direction) and the fit starts from random points; random points fit several dB worse than "
                      "SfM points (docs/fit.md, \"Initialisation\"): if you can, run COLMAP on the images and fit "
                      "from its points (morphgs fit --init points; curate's sparse:K fits start from random "
                      "points on purpose, since SfM points come from every view)", MorphgsWarning, stacklevel=3)


@contextlib.contextmanager
def random_init_on_purpose() -> Iterator[None]:
    """Fits inside it start from random points by design (the sparse fits of curate and ablate:
    SfM points would come from every view, not the few a sparse fit may see), so the
    forward-facing hint (`_warn_forward_facing`), which asks for SfM points, is not shown."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*the capture looks forward-facing", category=MorphgsWarning)
        yield


_PREV = "checkpoint.prev.bin"
_CUR = ".checkpoint.cur.bin"


def _keep_previous(ck_path: Path) -> None:
    """After a checkpoint is written: the one before it becomes checkpoint.prev.bin. Hard links
    (no copy): .checkpoint.cur.bin is a second name of the newest, renamed to prev at the next."""
    cur, prev = ck_path.with_name(_CUR), ck_path.with_name(_PREV)
    try:
        if cur.is_file():
            os.replace(cur, prev)
        os.link(ck_path, cur)
    except OSError:  # no hard links here: keep the newest only
        cur.unlink(missing_ok=True)


def _restore(core: Any, run: Path, train_imgs: Any, tw2c: Any, tk: Any, fp: bytes, common: dict[str, Any]) -> Any:
    """The trainer from the newest checkpoint that verifies (its checksum, its run), warning for a
    damaged one skipped; FitRunError naming them when none does."""
    damaged = []
    for ck in (run / "checkpoint.bin", run / _PREV):
        if not ck.is_file():
            continue
        try:
            trainer = core.Trainer.restore(ck, train_imgs, tw2c, tk, fingerprint=fp, **common)
        except MorphgsError as e:
            damaged.append(ck.name)
            warnings.warn(f"checkpoint {ck} is damaged ({e}); skipping it", MorphgsWarning, stacklevel=3)
            continue
        if damaged:  # resumed from the previous one: it is also the one to keep at the next checkpoint
            cur = run / _CUR
            cur.unlink(missing_ok=True)
            try:
                os.link(ck, cur)
            except OSError:
                pass
        return trainer
    raise FitRunError(f"{run}: no checkpoint verifies ({', '.join(damaged)} damaged); rerun with --restart "
                      "(resume=False) to start over")


def fit(
    data: str | os.PathLike[str] | PosedImages,
    out: str | os.PathLike[str],
    *,
    config: FitConfig | str | os.PathLike[str] | dict[str, Any] | None = None,
    views: str | Sequence[int] = "all",
    holdout: str | Sequence[int] = "every:8",
    init: Any = "auto",
    images: str | None = None,
    downscale: int = 1,
    steps: int | None = None,
    seed: int | None = None,
    resume: bool = True,
    progress: bool = True,
    callback: Callable[[str, Any], Any] | None = None,
    wait: bool = False,
    until: int | None = None,
) -> FitResult:
    """Fit a 3DGS scene to posed images on the CPU (docs/fit.md).

    Args:
        data: a transforms.json, a dataset folder (transforms.json or COLMAP model + images) or
            a `PosedImages`.
        out: the run folder (created; a rerun resumes in it).
        config: a FitConfig, a TOML file, a dict of settings, a preset name ("default",
            "mcmc", "sparse") or None (the defaults).
        views: training views: "all", "every:K", "n:N" or explicit indices (see
            morphgs.fit.views); holdout: "every:8" (default), "none" or explicit indices.
        init: "auto", "points", "random[:N]" (along the training rays), "box[:N]", "ply:PATH",
            "scene:PATH" or a GaussianScene.
        images: image folder to use instead of the dataset's (e.g. "images_4").
        downscale: shrink images (and cameras) by this integer factor.
        steps, seed: override the config's.
        resume: continue a run found in `out` (False: start over, removing its files).
        progress: show a progress bar (tqdm when installed) on stderr.
        callback: also called with every event of the loop (kind, payload); see
            `_core.Trainer.run`. A true return value stops the run after a checkpoint.
        wait: when another process writes `out`, wait for it instead of raising
            morphgs.reliability.FolderBusyError (the folder is locked while the fit runs).
        until: stop when this many steps are done (default: the config's steps). The schedule
            (learning-rate decay, densification, SH degree) stays that of the config's steps, so
            the result is the full fit's state at that step: a checkpoint and
            `point_cloud/iteration_<until>/` are written, fit.json is not (the run is not done),
            and a later call with a larger `until` (or none) resumes from there to the same bytes
            as an uninterrupted run. FitRunError when the run in `out` is already past it.

    Returns:
        FitResult.

    Raises:
        FileNotFoundError: missing dataset, images or init files. FitDataError, FitConfigError,
        ViewSelectionError, InitError (all MorphgsError): bad inputs, each naming the file or
        field. FitRunError: `out` holds another run. KeyboardInterrupt: Ctrl-C, after a
        checkpoint was written (rerun to resume).
    """
    with folder_lock(out, command="fit", wait=wait):
        return _fit(data, out, config=config, views=views, holdout=holdout, init=init, images=images,
                    downscale=downscale, steps=steps, seed=seed, resume=resume, progress=progress,
                    callback=callback, until=until)


def _fit(
    data: str | os.PathLike[str] | PosedImages,
    out: str | os.PathLike[str],
    *,
    config: FitConfig | str | os.PathLike[str] | dict[str, Any] | None = None,
    views: str | Sequence[int] = "all",
    holdout: str | Sequence[int] = "every:8",
    init: Any = "auto",
    images: str | None = None,
    downscale: int = 1,
    steps: int | None = None,
    seed: int | None = None,
    resume: bool = True,
    progress: bool = True,
    callback: Callable[[str, Any], Any] | None = None,
    until: int | None = None,
) -> FitResult:
    """`fit` with `out` locked (see there)."""
    from morphgs import _core
    from morphgs.fit.init import initial_scene
    from morphgs.fit.progress import progress_bar

    t_start = time.perf_counter()
    cfg = _resolve_config(config)
    if steps is not None or seed is not None:
        cfg = FitConfig.from_dict({**cfg.to_dict(), **({"steps": steps} if steps is not None else {}),
                                   **({"seed": seed} if seed is not None else {})})
    if downscale < 1:
        raise MorphgsError(f"downscale must be >= 1, got {downscale}")
    target = cfg.steps if until is None else int(until)
    if not 1 <= target <= cfg.steps:
        raise MorphgsError(f"until must be in [1, steps = {cfg.steps}], got {until}")
    posed = data if isinstance(data, PosedImages) else load_posed_images(data, images=images)
    sel: ViewSelection = select_views(len(posed), views, holdout=holdout)
    run = Path(out)
    run.mkdir(parents=True, exist_ok=True)
    cache = run / "undistorted"  # undistorted photos live in the run, never beside the user's data
    train_imgs, train_cams, train_masks = posed.read(sel.train, downscale=downscale, cache=cache)
    eval_imgs, eval_cams, eval_masks = posed.read(sel.heldout, downscale=downscale, cache=cache)
    scale = float(cfg.scene_scale) if not isinstance(cfg.scene_scale, str) else scene_scale_of(train_cams)
    native = cfg.native(scale)
    init_key = f"scene object {hashlib.sha256(np.asarray(init.means).tobytes()).hexdigest()[:16]}" \
        if isinstance(init, GaussianScene) else str(init)
    ident = {"config": native, "data": describe(posed), "train": sel.train, "heldout": sel.heldout,
             "downscale": downscale, "init": init_key, "format": 1}
    fingerprint = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()

    ck_path = run / "checkpoint.bin"
    id_path = run / "run.json"
    if id_path.is_file() and resume:
        old = json.loads(id_path.read_text(encoding="utf-8")).get("fingerprint")
        if old != fingerprint:
            raise FitRunError(f"{run} holds a run with another config, data, views or init; "
                              "use another folder, or resume=False (--restart) to start over")
    if not resume:
        for name in ("checkpoint.bin", _PREV, _CUR, "fit.json", "loss.csv", "eval.csv", "eval_views.csv", "run.json"):
            (run / name).unlink(missing_ok=True)
        for d in ("previews", "point_cloud"):
            shutil.rmtree(run / d, ignore_errors=True)

    ply = run / "point_cloud" / f"iteration_{cfg.steps}" / "point_cloud.ply"
    tw2c, tk = _stack(train_cams)
    ew2c, ek = _stack(eval_cams) if len(eval_cams) else (None, None)
    common: dict[str, Any] = dict(config=native, eval_images=list(eval_imgs), eval_world_to_camera=ew2c, eval_K=ek)
    if any(m is not None for m in train_masks + eval_masks):  # masked pixels: out of the loss and the metrics
        common["masks"] = [None if m is None else m.astype(np.uint8) for m in train_masks]
        common["eval_masks"] = [None if m is None else m.astype(np.uint8) for m in eval_masks]
    fp = fingerprint.encode()
    if (ck_path.is_file() or (run / _PREV).is_file()) and resume:
        trainer = _restore(_core, run, train_imgs, tw2c, tk, fp, common)
        init_desc = json.loads(id_path.read_text(encoding="utf-8")).get("init", init_key) if id_path.is_file() else init_key
    else:
        centers = np.stack([c.center for c in train_cams])
        _warn_forward_facing(init, posed, train_cams)
        scene0, init_desc = initial_scene(init, posed, centers, cfg, scene_scale=scale, train_cameras=train_cams,
                                          train_images=train_imgs, train_masks=train_masks)
        trainer = _core.Trainer(scene0, train_imgs, tw2c, tk, **common)
        _write_atomic(run / "config.toml", cfg.to_toml())
        names = posed.names
        _write_atomic(run / "views.json", json.dumps({
            "source": posed.source, "views": sel.spec, "holdout": sel.holdout, "downscale": downscale,
            "train": [{"index": i, "name": names[i]} for i in sel.train],
            "heldout": [{"index": i, "name": names[i]} for i in sel.heldout]}, indent=1) + "\n")
        all_cams = list(train_cams) + list(eval_cams)
        _write_atomic(run / "cameras.json", json.dumps(_inria_cameras(
            all_cams, [names[i] for i in sel.train + sel.heldout]), indent=1) + "\n")
        _write_atomic(id_path, json.dumps({"fingerprint": fingerprint, "init": init_desc, "scene_scale": scale,
                                           "identity": ident}, indent=1, sort_keys=True) + "\n")
    # the trainer holds its own copy of the pixels; keep only what the final preview needs
    first_train = (train_imgs[0], train_cams[0])
    del train_imgs
    start = trainer.step
    if start > target:
        raise FitPastError(f"{run}: the run is at step {start}, past the step asked for ({target}); "
                          "use another folder, or resume=False (--restart) to start over")
    _truncate_csv(run / "loss.csv", start, LOSS_COLUMNS)
    _truncate_csv(run / "eval.csv", start, EVAL_COLUMNS)
    _truncate_csv(run / "eval_views.csv", start, EVAL_VIEW_COLUMNS)

    score_lpips = _lpips_scorer(cfg.output.lpips, list(eval_imgs), verbose=progress, masks=eval_masks)
    bar = progress_bar(cfg.steps, start, progress)
    logger = _Logger(run, cfg, [posed.names[i] for i in sel.heldout], list(eval_imgs), bar, callback, progress,
                     score_lpips)
    t_run = time.perf_counter()
    try:
        ended = trainer.run(target, callback=logger, eval_every=cfg.output.eval_every if eval_imgs else 0,
                    checkpoint=ck_path, checkpoint_every=cfg.output.checkpoint_every, fingerprint=fp,
                    progress_every=cfg.output.progress_every)
    finally:
        logger.close()
        bar.close()
    run_s = time.perf_counter() - t_run
    done_steps = trainer.step - start

    scene = trainer.scene()
    done = ended == "finished" and trainer.step == cfg.steps
    if not done:  # stopped by the callback or at `until`: a PLY of where it is, no fit.json
        ply = run / "point_cloud" / f"iteration_{trainer.step}" / "point_cloud.ply"
    ply.parent.mkdir(parents=True, exist_ok=True)
    import morphgs

    morphgs.save_ply(scene, ply)
    metrics = trainer.evaluate() if eval_imgs else []
    psnr = float(np.mean([m[0] for m in metrics])) if metrics else None
    ssim = float(np.mean([m[1] for m in metrics])) if metrics else None
    lp_final = None
    if score_lpips is not None:
        lp_final = float(np.mean([score_lpips(trainer.render(np.ascontiguousarray(c.world_to_camera, np.float64),
                                                             np.ascontiguousarray(c.K, np.float64), c.width, c.height), v)
                                  for v, c in enumerate(eval_cams)]))
    # a final preview: first held-out view (else first training view) beside its image
    if eval_imgs:
        cam, truth = eval_cams[0], eval_imgs[0]
    else:
        truth, cam = first_train
    rgb = trainer.render(np.ascontiguousarray(cam.world_to_camera, np.float64),
                         np.ascontiguousarray(cam.K, np.float64), cam.width, cam.height)
    _core._write_png(run / "preview.png", _preview(rgb, truth))
    rate = done_steps / run_s if done_steps and run_s > 0 else None
    summary: dict[str, Any] = {"steps": trainer.step, "gaussians": len(scene), "heldout_psnr": psnr, "heldout_ssim": ssim,
               "heldout_lpips": lp_final, "train_views": len(sel.train), "heldout_views": len(sel.heldout), "scene_scale": scale,
               "init": init_desc, "strategy": cfg.strategy, "ply": str(ply.relative_to(run)),
               "seconds_this_call": round(time.perf_counter() - t_start, 3),
               "steps_this_call": done_steps,
               "steps_per_second": round(rate, 4) if rate is not None else None,
               "threads": _core.num_threads(), "morphgs_version": morphgs.__version__}
    if done:
        _write_atomic(run / "fit.json", json.dumps(summary, indent=1) + "\n")
    return FitResult(run, ply, scene, trainer.step, sel.train, sel.heldout, psnr, ssim, len(scene),
                     time.perf_counter() - t_start, round(rate, 4) if rate is not None else None, summary, lp_final)
