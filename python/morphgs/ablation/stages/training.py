"""Stage 3, training: one refiner per (condition, seed), all with the same budget and the same
seed stream (`morphgs.training.train` on the condition's training set), then the CKA probe.

- The run folder (`run/`) checkpoints every `probe_every` steps and keeps every checkpoint; a
  killed study resumes the run from its latest checkpoint, to the same bits (the training loop's
  resume guarantee), so the final weights do not depend on where it was killed.
- CKA (the paper's Fig. 5): on a fixed probe clip (the first `window` capture views of the first
  training scene, centre-cropped), the temporal-attention features of every checkpoint against
  the initial model's (the same weights the loop starts from: `torch.manual_seed(seed)`), linear
  CKA per module (Kornblith 2019) -> `cka.json`.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CKA_PATTERN", "IGNORE", "RESUMABLE", "VERSION", "cka_curve", "make", "overrides_for"]

VERSION = 2  # 2: the tiny refiner's SSIM term is 3DGS's (zero padding, the native kernel; docs/training.md)
IGNORE = ("threads",)
RESUMABLE = True  # the run resumes from its latest checkpoint, to the same bits

# tiny's temporal self-attention, and the motion modules' temporal attention of the diffusion refiners
CKA_PATTERN = r"(^|\.)attention$|motion_modules\.\d+\.transformer_blocks\.\d+\.attn1$"


def overrides_for(training: dict[str, Any], model_overrides: dict[str, Any], seed: int) -> dict[str, Any]:
    """The run overrides of a study's training settings (the model's own overrides first)."""
    from morphgs.configfile import merge

    ours = {
        "seed": int(seed),
        "data": {"frames": int(training["window"]), "size": list(training["crop"]), "num_workers": 0},
        "optim": {"max_steps": int(training["steps"]), "lr": float(training["lr"])},
        "run": {"mixed_precision": "no", "checkpoint_every": int(training["probe_every"]),
                "keep_checkpoints": 1_000_000, "validate_every": 0, "log_every": 1,
                "threads": int(training["threads"]), "time_limit": 0},
    }
    return merge(dict(model_overrides), ours)


def _probe_clip(probe_dir: Path, frames: int, crop: tuple[int, int]) -> np.ndarray:
    """The CKA probe: `frames` views of the capture `probe_dir` (its first run of consecutive
    views of its most common size: a capture of portrait and landscape photos keeps each photo's
    own orientation, and a clip must share one), centre-cropped to `crop` (H, W) or less."""
    from collections import Counter

    from morphgs import media

    views = [media.read_image(f) for f in media.frame_paths(probe_dir / "images")]
    size = Counter(v.shape[:2] for v in views).most_common(1)[0][0]
    same = [v.shape[:2] == size for v in views]
    start = next((i for i in range(len(views) - frames + 1) if all(same[i:i + frames])), None)
    picked = views[start:start + frames] if start is not None else [v for v, s in zip(views, same) if s][:frames]
    clip = np.stack(picked)
    h, w = min(crop[0], size[0]), min(crop[1], size[1])
    y0, x0 = (clip.shape[1] - h) // 2, (clip.shape[2] - w) // 2
    return np.ascontiguousarray(clip[:, y0:y0 + h, x0:x0 + w])


def cka_curve(run_dir: Path, probe: np.ndarray, *, max_rows: int) -> dict[str, Any]:
    """{"steps": [0, s1, ...], "cka": {module: [1.0, ...]}, "mean": [...]} of a finished run."""
    import torch

    from morphgs.inference import to_model, load_run
    from morphgs.metrics import linear_cka
    from morphgs.metrics.features import FeatureRecorder
    from morphgs.models.base import ModelContext
    from morphgs.models.registry import create_model
    from morphgs.training.checkpoint import list_checkpoints
    from morphgs.training.config import TrainConfig
    from morphgs.training.loop import read_run_file

    cfg = TrainConfig.from_dict(read_run_file(run_dir)["config"], source=str(run_dir / "run.json"))
    ctx = ModelContext(frames=cfg.data.frames, size=cfg.data.size, reference=cfg.data.reference, training=False,
                       run_dir=run_dir, cache_dir=run_dir / "cache")
    torch.manual_seed(cfg.seed)  # the loop's initial weights
    initial = create_model(cfg.model, cfg.model_config, ctx).eval()
    x = to_model(probe, torch.device("cpu"))

    def features(model: Any) -> dict[str, np.ndarray]:
        rec = FeatureRecorder(model, pattern=CKA_PATTERN, max_rows=max_rows, seed=0)
        return rec.record(lambda: model.refine(x))

    ref = features(initial)
    steps = [0]
    per = {name: [1.0] for name in ref}
    every, last = cfg.run.checkpoint_every, cfg.optim.max_steps
    for step, ckpt in list_checkpoints(run_dir):
        if every and step % every and step != last:
            continue  # a stop's checkpoint (SIGTERM), kept to resume from, is not a probe point
        feats = features(load_run(run_dir, checkpoint=ckpt, device="cpu").model)
        steps.append(int(step))
        for name in ref:
            per[name].append(float(linear_cka(ref[name], feats[name])))
    mean = [float(np.mean([per[n][i] for n in per])) for i in range(len(steps))]
    return {"steps": steps, "cka": per, "mean": mean, "probe": list(probe.shape)}


def make(work: Path, *, data: str, model: str, model_config: str, overrides: dict[str, Any], probe_dir: str,
         probe_rows: int, threads: int) -> None:
    """Train (or resume) `work/run`, then write `work/cka.json` and `work/train.json`."""
    import shutil

    from morphgs.ablation.stages.common import torch_threads
    from morphgs.training import train
    from morphgs.training.checkpoint import latest_checkpoint

    torch_threads(threads)
    d = overrides["data"]
    crop_h, crop_w = (int(v) for v in d["size"])
    probe = _probe_clip(Path(probe_dir), int(d["frames"]), (crop_h, crop_w))
    run = work / "run"
    resume = run.is_dir() and latest_checkpoint(run) is not None
    if run.exists() and not resume:  # killed before its first checkpoint: start over
        shutil.rmtree(run)
    result = train(data, out=run, model=model, config=model_config or None, overrides=overrides, resume=resume,
                   progress=False, log=lambda m: None)
    if result.stopped_early:
        # SIGTERM / Ctrl-C reached the training loop, which checkpointed and returned: stop the
        # study here, so that this half-trained run is never taken for a finished stage (the work
        # folder keeps its checkpoint and the rerun continues from it)
        from morphgs.reliability import Preempted

        if result.preempted == "SIGTERM":
            raise Preempted(signal.SIGTERM)
        raise KeyboardInterrupt(f"training stopped early at step {result.steps} ({result.preempted or 'time limit'})")
    (work / "train.json").write_text(json.dumps({"steps": result.steps, "resumed": resume}, indent=1) + "\n",
                                     encoding="utf-8")
    curve = cka_curve(run, probe, max_rows=probe_rows)
    (work / "cka.json").write_text(json.dumps(curve, indent=1, sort_keys=True) + "\n", encoding="utf-8")
