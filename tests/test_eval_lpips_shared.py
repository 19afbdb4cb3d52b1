"""`morphgs eval --run` scores the input and the output against one clean clip: the clean clip's
LPIPS features are computed once for both (3 feature passes instead of 4), with the values of
scoring each pair alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from metrics_data import guitar_pair

from PIL import Image

from morphgs import metrics
from morphgs.evaluation import ClipPair, evaluate
from morphgs.metrics.perceptual import lpips_many


def _clips() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pair = guitar_pair()
    u8 = lambda a: np.rint(np.clip(a, 0, 1) * 255).astype(np.uint8)  # noqa: E731
    gt = u8(pair.clean.rgb)
    inp = u8(pair.corrupted.rgb)
    out = u8(0.5 * pair.corrupted.rgb + 0.5 * pair.clean.rgb)
    return inp, out, gt


class _ImagesSeen:
    """Counts the images the LPIPS trunk's first layer sees (one per image per feature pass)."""

    def __init__(self) -> None:
        self.n = 0
        model = metrics.lpips_model("alex")
        self.handle = model.features[0].register_forward_hook(self._hook)

    def _hook(self, _mod: object, args: tuple[object, ...], _out: object) -> None:
        self.n += int(args[0].shape[0])  # type: ignore[attr-defined]

    def __enter__(self) -> _ImagesSeen:
        return self

    def __exit__(self, *exc: object) -> None:
        self.handle.remove()


def test_lpips_many_gives_each_pairs_values_with_the_target_seen_once() -> None:
    inp, out, gt = _clips()
    with _ImagesSeen() as seen:
        a, b = lpips_many([inp, out], gt, batch_size=3)
    assert seen.n == 3 * len(gt)
    with _ImagesSeen() as seen:
        want_a = metrics.lpips(inp, gt, reduction="none")
        want_b = metrics.lpips(out, gt, reduction="none")
    assert seen.n == 4 * len(gt)
    np.testing.assert_allclose(a, want_a, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b, want_b, rtol=1e-5, atol=1e-6)
    assert np.all(b < a)  # the output is closer to the target than the input
    assert lpips_many([], gt) == []


def test_evaluate_shares_the_target_of_consecutive_pairs_on_disk(tmp_path: Path) -> None:
    inp, out, gt = _clips()
    for name, clip in (("in", inp), ("out", out), ("gt", gt)):
        (tmp_path / name).mkdir()
        for i, frame in enumerate(clip):
            Image.fromarray(frame).save(tmp_path / name / f"{i:05d}.png")
    pairs = [ClipPair("p", tmp_path / "in", tmp_path / "gt", label="input"),
             ClipPair("p", tmp_path / "out", tmp_path / "gt", label="output")]
    with _ImagesSeen() as seen:
        shared = evaluate(pairs, metrics=("lpips", "psnr"), progress=False)
    assert seen.n == 3 * len(gt)
    with _ImagesSeen() as seen:
        alone = [evaluate([p], metrics=("lpips", "psnr"), progress=False) for p in pairs]
    assert seen.n == 4 * len(gt)
    got = {r["label"]: r for r in shared.clips}
    for rep, label in zip(alone, ("input", "output")):
        assert abs(got[label]["lpips"] - rep.clips[0]["lpips"]) < 1e-6
        assert got[label]["psnr"] == rep.clips[0]["psnr"]
    # a pair whose prediction does not load is reported in its own turn, in its own name
    (tmp_path / "empty").mkdir()
    bad = [pairs[0], ClipPair("q", tmp_path / "empty", tmp_path / "gt", label="output")]
    try:
        evaluate(bad, metrics=("lpips",), progress=False)
    except Exception as e:  # noqa: BLE001 - the type is media's or eval's, the name is what matters
        assert "empty" in str(e) or "q" in str(e)
    else:
        raise AssertionError("an empty clip folder must raise")
