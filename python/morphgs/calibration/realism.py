"""Can a classifier tell synthetic pairs from real ones? A CNN two-sample test (docs/calibration.md,
"Realism").

The hand-picked statistics of `goodness` see how much error a pair has and in which frequency
bands; a small convolutional network sees its shape: floaters, needles and speckle against holes
and blobs. It takes a frame's clean render and its residual (corrupted - clean), six channels,
and says how likely the frame is synthetic.

The test:

- **train** on the training pairs (the calibration scenes), real frames labelled 0 and synthetic
  ones 1, random crops of `CROP` pixels flipped at random, balanced batches; **score** every frame
  of the test pairs (the held-out scenes) whole (the network is fully convolutional and averages
  over the frame). With no held-out scene, the pairs are cross-fitted: two folds by alternate
  pair, each scored by a network trained on the other.
- **AUC** of the frames' scores (0.5: the network cannot tell them apart; 1.0: it always can) and
  a bootstrap 95 % interval resampling scenes (or pairs, with one scene), since the frames of a
  scene are not independent.
- **the real-vs-real floor**: the same network, data size and folds asked to tell two halves of the
  real pairs apart (alternate pairs within each scene, so both halves hold the same scenes); its
  AUC is what "indistinguishable" looks like with this many pairs.

Deterministic: seeded (torch and NumPy), torch on one thread while it runs (its CPU convolutions
may sum in another order on more), so the same pairs give the same AUC on every machine of the
same kind. Needs torch (`pip install 'morphgs[metrics]'`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from morphgs.calibration.goodness import auc, bootstrap_auc, separation

__all__ = ["CROP", "REPEAT_STRIDE", "STEPS", "Clip", "classifier_test", "floor_test", "realism_test"]

#: Side of the training crops, in pixels (smaller frames are used whole).
CROP = 48
#: Training steps of one network.
STEPS = 240
#: Crops per training batch (half real, half synthetic).
BATCH = 32
#: Seed offset between the networks of one fold when `repeats` > 1.
REPEAT_STRIDE = 7919


@dataclass(frozen=True)
class Clip:
    """One pair as the classifier sees it: corrupted and clean frames (F, H, W, 3) in [0, 1], its
    scene (the bootstrap's unit) and its label (0 real, 1 synthetic)."""

    corrupted: np.ndarray
    clean: np.ndarray
    scene: str
    label: int


@contextmanager
def _one_thread() -> Iterator[None]:
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _inputs(clip: Clip) -> np.ndarray:
    """(F, 6, H, W) float32: the clean frame in [-1, 1] and the residual times 4."""
    clean = np.asarray(clip.clean, dtype=np.float32)
    res = np.asarray(clip.corrupted, dtype=np.float32) - clean
    x = np.concatenate([clean * 2.0 - 1.0, res * 4.0], axis=-1)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))


def _network() -> Any:
    from torch import nn

    def block(i: int, o: int, stride: int) -> list[Any]:
        return [nn.Conv2d(i, o, 3, stride=stride, padding=1), nn.GroupNorm(8, o), nn.SiLU()]

    return nn.Sequential(*block(6, 32, 2), *block(32, 32, 1), *block(32, 64, 2), *block(64, 64, 2),
                         nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(64, 1))


def _train(frames: Sequence[np.ndarray], labels: Sequence[int], *, seed: int, steps: int) -> Any:
    """A network trained to tell label-1 frames from label-0 ones (`frames`: (F, 6, H, W) per clip)."""
    import torch

    torch.manual_seed(seed)
    net = _network()
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
    rng = np.random.default_rng(seed)
    by_label = {c: [(i, f) for i, lab in enumerate(labels) if lab == c for f in range(len(frames[i]))] for c in (0, 1)}
    h, w = frames[0].shape[2:]
    ch, cw = min(CROP, h), min(CROP, w)
    half = BATCH // 2
    net.train()
    for _ in range(steps):
        batch, target = [], []
        for c in (0, 1):
            pool = by_label[c]
            for k in rng.integers(0, len(pool), size=half):
                i, f = pool[int(k)]
                y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
                crop = frames[i][f, :, y0:y0 + ch, x0:x0 + cw]
                if rng.random() < 0.5:
                    crop = crop[:, :, ::-1]
                batch.append(crop)
                target.append(float(c))
        x = torch.from_numpy(np.ascontiguousarray(np.stack(batch)))
        y = torch.tensor(target)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(net(x).squeeze(1), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    return net


def _score(net: Any, frames: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        return net(torch.from_numpy(frames)).squeeze(1).numpy().astype(np.float64)  # type: ignore[no-any-return]


def classifier_test(train: Sequence[Clip], test: Sequence[Clip] | None = None, *, seed: int = 0,
                    steps: int = STEPS, n_boot: int = 200, repeats: int = 1) -> dict[str, Any]:
    """The CNN two-sample test (module doc): trained on `train`, scored on `test`; with no `test`,
    `train` is cross-fitted in two folds by alternate clip of each label. `repeats` > 1 trains that
    many networks per fold (seeds `seed + fold + REPEAT_STRIDE * j`, the first the single
    network's) and scores each frame by their mean logit: an ensemble, steadier from seed to seed
    than one network (docs/calibration.md, "Realism").

    Returns {"auc", "ci", "separation", "bootstrap": "scenes" | "pairs", "frames": {"real",
    "synthetic"}, "held_out": bool, "steps"} (and "repeats" when > 1); "separation" is the tested
    frames' logits' d' (`goodness.separation`), which still ranks families the AUC calls equal
    when every frame is told apart.

    Raises:
        ValueError: a side without both labels, clips of different frame sizes, or repeats < 1.
    """
    try:
        import torch  # noqa: F401
    except ImportError as e:  # pragma: no cover - metrics extra missing
        raise ImportError("the realism classifier needs torch: pip install 'morphgs[metrics]'") from e
    if repeats < 1:
        raise ValueError(f"the classifier's repeats must be >= 1, got {repeats}")
    clips = list(train) + list(test or [])
    if len({c.clean.shape[1:3] for c in clips}) != 1:
        raise ValueError(f"the classifier's clips differ in frame size: {sorted({c.clean.shape[1:3] for c in clips})}")
    for name, side in (("training", train), ("test", test)):
        if side is not None and {c.label for c in side} != {0, 1}:
            raise ValueError(f"the classifier's {name} clips need both real (0) and synthetic (1) ones")
    frames = [_inputs(c) for c in clips]
    n_train = len(train)
    if test:
        folds = [(list(range(n_train)), list(range(n_train, len(clips))))]
    else:
        rank = np.zeros(n_train, dtype=int)
        for lab in (0, 1):
            idx = [i for i, c in enumerate(train) if c.label == lab]
            rank[idx] = np.arange(len(idx))
        odd = [i for i in range(n_train) if rank[i] % 2]
        even = [i for i in range(n_train) if not rank[i] % 2]
        folds = [(even, odd), (odd, even)]
        if any({clips[i].label for i in tr} != {0, 1} for tr, _ in folds):
            raise ValueError("cross-fitting needs at least two real and two synthetic clips")
    scores, labels, units = [], [], []
    with _one_thread():
        for k, (tr, te) in enumerate(folds):
            nets = [_train([frames[i] for i in tr], [clips[i].label for i in tr], seed=seed + k + REPEAT_STRIDE * j,
                           steps=steps) for j in range(repeats)]
            for i in te:
                s = _score(nets[0], frames[i])
                for net in nets[1:]:
                    s = s + _score(net, frames[i])
                if repeats > 1:
                    s = s / repeats
                scores.append(s)
                labels.append(np.full(len(s), clips[i].label))
                units.append(np.full(len(s), i))
    sc, lb, un = np.concatenate(scores), np.concatenate(labels), np.concatenate(units)
    tested = [clips[i] for _, te in folds for i in te]
    scenes = sorted({c.scene for c in tested})
    if len(scenes) > 1:
        scene_of = {i: clips[i].scene for _, te in folds for i in te}
        un = np.array([scene_of[int(u)] for u in un])
    value = auc(sc, lb)
    out = {"auc": value, "ci": bootstrap_auc(sc, lb, un, n_boot=n_boot, seed=seed), "separation": separation(sc, lb),
           "bootstrap": "scenes" if len(scenes) > 1 else "pairs",
           "frames": {"real": int(np.sum(lb == 0)), "synthetic": int(np.sum(lb == 1))},
           "held_out": bool(test), "steps": int(steps)}
    if repeats > 1:
        out["repeats"] = int(repeats)
    return out


def _halves(clips: Sequence[Clip], seed: int) -> list[Clip]:
    """The real clips relabelled into two halves: within each scene, its clips in a seeded random
    order alternate between the halves (balanced, and independent of how the clips were made)."""
    rng = np.random.default_rng(seed)
    label = [0] * len(clips)
    for scene in sorted({c.scene for c in clips}):
        idx = [i for i, c in enumerate(clips) if c.scene == scene]
        for k, i in enumerate(rng.permutation(idx)):
            label[int(i)] = k % 2
    return [Clip(c.corrupted, c.clean, c.scene, lab) for c, lab in zip(clips, label)]


def floor_test(train_real: Sequence[Clip], test_real: Sequence[Clip] | None = None, *, seed: int = 0,
               steps: int = STEPS, n_boot: int = 200, repeats: int = 1) -> dict[str, Any]:
    """The real-vs-real floor: `classifier_test` between two halves of the real clips (`_halves`). NaN (and a reason) when a side has too few clips to split."""
    tr = _halves(train_real, seed)
    te = _halves(test_real, seed + 1) if test_real else None
    need_tr = 2 if te else 4
    if sum(c.label == 0 for c in tr) < need_tr // 2 or sum(c.label == 1 for c in tr) < need_tr // 2 or \
            (te is not None and {c.label for c in te} != {0, 1}):
        return {"auc": float("nan"), "ci": [float("nan"), float("nan")], "bootstrap": "none",
                "reason": "too few real pairs per scene to split into two halves", "held_out": bool(te),
                "steps": int(steps)}
    return classifier_test(tr, te, seed=seed, steps=steps, n_boot=n_boot, repeats=repeats)


def realism_test(train_real: Sequence[Clip], train_synth: Sequence[Clip], test_real: Sequence[Clip] | None = None,
                 test_synth: Sequence[Clip] | None = None, *, seed: int = 0, steps: int = STEPS,
                 floor: bool = True, repeats: int = 1) -> dict[str, Any]:
    """Synthetic against real (`classifier_test`) and, with `floor`, the real-vs-real floor
    (`floor_test`) on the same scenes, each with `repeats` networks per fold: {"classifier": ...,
    "floor": ...}."""
    test = (list(test_real) + list(test_synth)) if test_real and test_synth else None
    out = {"classifier": classifier_test(list(train_real) + list(train_synth), test, seed=seed, steps=steps,
                                         repeats=repeats)}
    if floor:
        out["floor"] = floor_test(train_real, test_real if test else None, seed=seed, steps=steps, repeats=repeats)
    return out
