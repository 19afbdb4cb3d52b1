"""Linear CKA: invariances, the Gram-matrix definition, minibatch accumulation, and the
temporal-attention feature recorder on a real (tiny) AnimateDiff UNet trained for real steps."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from morphgs import metrics
from morphgs.metrics import FeatureHistory, FeatureRecorder, MetricError, MinibatchCKA


def _features(n: int = 200, p: int = 12, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, p)) @ rng.normal(size=(p, p)) + rng.normal(size=p)


def _gram_cka(x: np.ndarray, y: np.ndarray) -> float:
    """CKA from its definition: HSIC(K, L) / sqrt(HSIC(K, K) HSIC(L, L)) with centred Gram matrices."""
    n = len(x)
    h = np.eye(n) - 1.0 / n
    k, l = h @ x @ x.T @ h, h @ y @ y.T @ h  # noqa: E741
    return float((k * l).sum() / np.sqrt((k * k).sum() * (l * l).sum()))


def test_cka_matches_its_gram_matrix_definition() -> None:
    x, y = _features(seed=0), _features(seed=1)[:, :7]
    y = y + 0.5 * x[:, :7]
    assert metrics.linear_cka(x, y) == pytest.approx(_gram_cka(x, y), rel=1e-10)
    assert 0.0 < metrics.linear_cka(x, y) < 1.0


@pytest.mark.parametrize("debiased", [False, True])
def test_cka_invariances(debiased: bool) -> None:
    x = _features()
    q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(12, 12)))   # a random orthogonal matrix
    assert metrics.linear_cka(x, x, debiased=debiased) == pytest.approx(1.0, abs=1e-12)
    assert metrics.linear_cka(x, x @ q, debiased=debiased) == pytest.approx(1.0, abs=1e-10)
    assert metrics.linear_cka(x, -3.5 * x + 7.0, debiased=debiased) == pytest.approx(1.0, abs=1e-10)
    independent = metrics.linear_cka(x, _features(seed=9), debiased=debiased)
    assert abs(independent) < 0.15


def test_minibatch_cka_accumulates_the_unbiased_estimate() -> None:
    x = _features(n=240)
    y = np.tanh(x[:, :5]) + 0.3 * _features(n=240, seed=5)[:, :5]
    one = MinibatchCKA()
    one.update(x, y)
    assert one.compute() == pytest.approx(metrics.linear_cka(x, y, debiased=True), rel=1e-9)
    batched = MinibatchCKA()
    for s in range(0, 240, 60):
        batched.update(x[s:s + 60], y[s:s + 60])
    assert batched.batches == 4 and abs(batched.compute() - one.compute()) < 0.05
    q, _ = np.linalg.qr(np.random.default_rng(4).normal(size=(12, 12)))
    inv = MinibatchCKA()
    for s in range(0, 240, 60):
        inv.update(x[s:s + 60], 2.0 * x[s:s + 60] @ q + 1.0)
    assert inv.compute() == pytest.approx(1.0, abs=1e-10)
    assert np.isnan(MinibatchCKA().compute())


def test_cka_accepts_torch_and_rejects_mismatched_rows() -> None:
    x = _features()
    assert metrics.linear_cka(torch.from_numpy(x), x) == pytest.approx(1.0)
    with pytest.raises(MetricError, match="same examples"):
        metrics.linear_cka(x, x[:-1])
    with pytest.raises(MetricError, match="at least 4"):
        MinibatchCKA().update(x[:3], x[:3])


def _tiny_motion_unet() -> torch.nn.Module:
    """diffusers' own test configuration of UNetMotionModel (tests/models/unets/test_models_unet_motion.py)."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from diffusers import UNetMotionModel

    torch.manual_seed(0)
    return UNetMotionModel(
        block_out_channels=(16, 32), norm_num_groups=16,
        down_block_types=("CrossAttnDownBlockMotion", "DownBlockMotion"),
        up_block_types=("UpBlockMotion", "CrossAttnUpBlockMotion"),
        cross_attention_dim=16, num_attention_heads=2, in_channels=4, out_channels=4,
        layers_per_block=1, sample_size=16,
    )


def test_temporal_attention_features_drift_over_real_training_steps() -> None:
    unet = _tiny_motion_unet()
    g = torch.Generator().manual_seed(1)
    sample = torch.randn(1, 4, 4, 16, 16, generator=g)                # (B, C, F, H, W)
    text = torch.randn(4, 4, 16, generator=g)                        # (B*F, L, D)
    target = torch.randn(1, 4, 4, 16, 16, generator=g)
    timestep = torch.tensor([10])

    def probe() -> None:
        unet(sample, timestep, encoder_hidden_states=text)

    history = FeatureHistory(unet, probe, max_rows=256)
    names = history.recorder.names
    assert len(names) == 7 and all(n.endswith("attn1") and "motion_modules" in n for n in names)
    first = history.snapshot(step=0)
    again = FeatureRecorder(unet, max_rows=256).record(probe)
    for n in names:
        assert first[n].ndim == 2 and first[n].shape[0] <= 256 and first[n].dtype == np.float64
        np.testing.assert_array_equal(first[n], again[n])             # same probe, same rows, same features
    assert not any(m._forward_hooks for m in unet.modules())          # hooks are removed after recording

    unet.train()
    opt = torch.optim.AdamW(unet.parameters(), lr=1e-2)
    for step in (1, 2):
        loss = torch.nn.functional.mse_loss(unet(sample, timestep, encoder_hidden_states=text).sample, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.snapshot(step=step)
    assert unet.training                                              # the recorder restored the mode

    cka = history.cka()
    assert history.steps == [0, 1, 2] and set(cka) == set(names)
    for n in names:
        values = cka[n]
        assert values[0] == pytest.approx(1.0)
        assert all(0.0 < v < 1.0 - 1e-6 for v in values[1:]), (n, values)
    drift = [np.mean([cka[n][s] for n in names]) for s in (1, 2)]
    assert drift[1] < drift[0]                                        # further from the start after more steps


def test_recorder_needs_a_matching_module() -> None:
    with pytest.raises(MetricError, match="no submodule"):
        FeatureRecorder(torch.nn.Linear(3, 3))
