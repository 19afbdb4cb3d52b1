"""The model registry and the tiny refiner: lookups, size, identity at initialisation, any clip
length, reference frames, and what training changed saved and restored exactly."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from morphgs.models import (CheckpointError, ModelContext, UnknownModelError, create_model, get_model,
                            list_models)
from morphgs.models.tiny import count_parameters
from morphgs.training import resolve_config
from train_helpers import SMALL_MODEL


def test_registry_names_the_models_and_refuses_unknown_ones() -> None:
    assert {"tiny", "sandbox", "controlnet"} <= set(list_models())
    assert get_model("tiny").config == "tiny.toml"
    with pytest.raises(UnknownModelError, match="unknown model 'nope'; known models: .*tiny"):
        get_model("nope")


def test_the_default_tiny_is_a_few_million_parameters_and_starts_as_the_identity() -> None:
    cfg = resolve_config("tiny", None).config
    torch.manual_seed(0)
    model = create_model("tiny", cfg.model_config, ModelContext(frames=16))
    assert 2_000_000 < count_parameters(model) < 5_000_000
    x = torch.rand(1, 3, 5, 32, 64) * 2 - 1  # any frame count; H, W multiples of 32
    assert torch.equal(model.refine(x), x)
    loss, logs = model({"corrupted": x, "clean": x})
    assert float(loss.detach()) == pytest.approx(0.0, abs=1e-6) and float(logs["ssim"]) == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ValueError, match="divisible by 32"):
        model.refine(torch.zeros(1, 3, 2, 40, 64))


def test_reference_frames_feed_the_model_only_when_it_was_built_for_them() -> None:
    torch.manual_seed(0)
    model = create_model("tiny", SMALL_MODEL, ModelContext(frames=4, reference=2))
    x, ref = torch.rand(2, 3, 4, 16, 16) * 2 - 1, torch.rand(2, 3, 2, 16, 16) * 2 - 1
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    for _ in range(2):  # the zero-initialised head passes gradients back only after a first step
        opt.zero_grad()
        loss, _ = model({"corrupted": x, "clean": x * 0.5, "reference": ref})
        loss.backward()
        opt.step()
    assert model.net.ref_proj.weight.grad.abs().sum() > 0
    with torch.no_grad():
        assert not torch.equal(model.refine(x, reference=ref), model.refine(x, reference=ref.flip(0)))
    with pytest.raises(ValueError, match="reference"):
        model.refine(x)


def test_trained_weights_round_trip_and_refuse_another_config(tmp_path: Path) -> None:
    torch.manual_seed(0)
    a = create_model("tiny", SMALL_MODEL, ModelContext(frames=4))
    with torch.no_grad():
        for p in a.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    a.save_trained(tmp_path)
    torch.manual_seed(1)
    b = create_model("tiny", SMALL_MODEL, ModelContext(frames=4))
    b.load_trained(tmp_path)
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    wider = create_model("tiny", {**SMALL_MODEL, "channels": [8, 24]}, ModelContext(frames=4))
    with pytest.raises(CheckpointError, match="trained.safetensors.*shape"):
        wider.load_trained(tmp_path)
    with pytest.raises(FileNotFoundError, match="trained.safetensors"):
        b.load_trained(tmp_path / "nowhere")
