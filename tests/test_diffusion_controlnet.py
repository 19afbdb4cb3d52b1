"""The dilated ControlNet on a frozen Wan DiT: block copies, exact identity at init, residual
placement, gradients, expert routing; the flow-matching objective. Tiny random Wan models saved in
diffusers layout (tests/tiny_diffusion.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")


from morphgs.diffusion import ModelFolderError  # noqa: E402
from morphgs.diffusion import tiny as td  # noqa: E402
from morphgs.diffusion import objectives, wan  # noqa: E402
from morphgs.diffusion.controlnet import DilatedControlNet, controlled_forward  # noqa: E402


@pytest.fixture(scope="module")
def a14b(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return td.wan_folder(tmp_path_factory.mktemp("wan") / "a14b")


@pytest.fixture(scope="module")
def parts(a14b: Path):
    return wan.load_wan(a14b, dtype=torch.float32)


def _inputs(batch: int = 2, channels: int = 16, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, channels, 2, 4, 4, generator=g)
    text = torch.randn(batch, 6, td.TEXT_DIM, generator=g)
    control = torch.randn(batch, channels, 2, 4, 4, generator=g)
    return x, text, control


def test_both_experts_and_the_boundary_load_from_the_folder(parts) -> None:
    assert len(parts.experts) == 2 and parts.boundary_ratio == 0.875
    a, b = (dict(e.named_parameters()) for e in parts.experts)
    assert not torch.equal(a["blocks.0.attn1.to_q.weight"], b["blocks.0.attn1.to_q.weight"])
    assert all(not p.requires_grad for e in parts.experts for p in e.parameters())


def test_copied_blocks_equal_base_blocks_at_stride_bit_for_bit(parts, tmp_path: Path) -> None:
    base = parts.experts[0]
    net = DilatedControlNet.from_transformer(base, num_blocks=3, stride=3)
    assert net.layers == [0, 3, 6]
    net.save_pretrained(tmp_path / "cn")
    back = DilatedControlNet.from_pretrained(tmp_path / "cn", local_files_only=True)
    for copy in (net, back):
        for i, j in enumerate([0, 3, 6]):
            mine, theirs = copy.blocks[i].state_dict(), base.blocks[j].state_dict()
            assert mine.keys() == theirs.keys()
            assert all(torch.equal(mine[k], theirs[k]) for k in theirs), (i, j)
        assert all(not p.any() for m in [copy.control_embedding, *copy.proj_out] for p in m.parameters())
    # and not the blocks TheDenk's init copies (0, 1, 2)
    assert not torch.equal(net.blocks[1].ffn.net[0].proj.weight, base.blocks[1].ffn.net[0].proj.weight)


def test_paper_layout_is_blocks_0_to_21_of_a_40_block_base() -> None:
    net = DilatedControlNet(num_blocks=8, stride=3, num_attention_heads=2, attention_head_dim=8, ffn_dim=8,
                            base_num_layers=40)
    assert net.layers == [0, 3, 6, 9, 12, 15, 18, 21]
    with pytest.raises(ValueError, match="reach base block 21"):
        DilatedControlNet(num_blocks=8, stride=3, num_attention_heads=2, attention_head_dim=8, ffn_dim=8,
                          base_num_layers=20)


@pytest.mark.parametrize("expert", [0, 1])
def test_output_at_init_equals_the_base_output_exactly(parts, expert: int) -> None:
    base = parts.experts[expert]
    net = DilatedControlNet.from_transformer(parts.experts[0], num_blocks=3, stride=3)
    x, text, control = _inputs()
    t = torch.tensor([950.0, 400.0])
    with torch.no_grad():
        want = base(x, t, text).sample
        got = controlled_forward(base, net, x, t, text, control)
    assert torch.equal(got, want)


def test_output_at_init_equals_the_base_for_per_token_timesteps(tmp_path: Path) -> None:
    p = wan.load_wan(td.wan_folder(tmp_path / "ti2v", experts=1, ti2v=True), dtype=torch.float32)
    assert p.expand_timesteps and p.boundary_ratio is None
    base = p.experts[0]
    net = DilatedControlNet.from_transformer(base, num_blocks=2, stride=3)
    x, text, control = _inputs(channels=48)
    t = wan.timestep_input(torch.tensor([700.0, 30.0]), x.shape, base.config.patch_size, expand=True)
    assert t.shape == (2, 2 * 2 * 2)
    with torch.no_grad():
        assert torch.equal(controlled_forward(base, net, x, t, text, control), base(x, t, text).sample)


def test_residual_i_is_added_after_base_block_stride_times_i(parts) -> None:
    base = parts.experts[1]
    net = DilatedControlNet.from_transformer(parts.experts[0], num_blocks=3, stride=3)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for m in [net.control_embedding, *net.proj_out]:
            m.weight.copy_(0.05 * torch.randn(m.weight.shape, generator=g))
    x, text, control = _inputs()
    t = torch.tensor([100.0, 300.0])
    captured: dict[str, object] = {}

    def grab(_mod, args, kwargs=None):
        captured["args"] = args

    h = base.blocks[0].register_forward_pre_hook(grab)
    with torch.no_grad():
        base(x, t, text)
    h.remove()
    hidden, text_emb, tproj, rope = captured["args"]
    with torch.no_grad():
        residuals = net(hidden, control, text_emb, tproj, rope)
    hooks = [base.blocks[3 * i].register_forward_hook(lambda _m, _a, out, r=r: out + 0.5 * r)
             for i, r in enumerate(residuals)]
    try:
        with torch.no_grad():
            want = base(x, t, text).sample
    finally:
        for hk in hooks:
            hk.remove()
    with torch.no_grad():
        got = controlled_forward(base, net, x, t, text, control, scale=0.5)
        plain = base(x, t, text).sample
    assert torch.allclose(got, want, atol=1e-6)
    assert not torch.allclose(got, plain, atol=1e-3)


@pytest.mark.parametrize("checkpointing", [False, True])
def test_only_controlnet_parameters_get_gradients(parts, checkpointing: bool) -> None:
    base = parts.experts[0]
    net = DilatedControlNet.from_transformer(base, num_blocks=3, stride=3)
    net.train()
    x, text, control = _inputs()
    out = controlled_forward(base, net, x, torch.tensor([900.0, 880.0]), text, control,
                             gradient_checkpointing=checkpointing)
    out.square().mean().backward()
    assert all(p.grad is None and not p.requires_grad for e in parts.experts for p in e.parameters())
    assert all(p.grad is not None for p in net.parameters())
    # at init only the zero output projections see a non-zero gradient
    assert all(m.weight.grad.abs().sum() > 0 for m in net.proj_out)


def test_expert_routing_follows_the_boundary() -> None:
    t = torch.tensor([999.0, 875.0, 874.9, 10.0])
    assert wan.expert_index(t, 0.875).tolist() == [0, 0, 1, 1]
    assert wan.expert_index(t, None).tolist() == [0, 0, 0, 0]


def test_incomplete_wan_folders_are_named(a14b: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        wan.load_wan(tmp_path / "missing")
    broken = shutil.copytree(a14b, tmp_path / "broken")
    shutil.rmtree(broken / "transformer_2")
    with pytest.raises(ModelFolderError, match="transformer_2/ is missing"):
        wan.load_wan(broken)
    (broken / "text_encoder" / "model.safetensors").unlink()
    with pytest.raises(ModelFolderError, match="text_encoder/model.safetensors"):
        wan.load_wan(broken)
    index = json.loads((a14b / "model_index.json").read_text())
    assert index["boundary_ratio"] == 0.875


def test_flow_matching_inputs_and_shifted_sigmas_match_the_scheduler() -> None:
    from diffusers import FlowMatchEulerDiscreteScheduler

    s = FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=5.0)
    u = torch.linspace(1.0, 0.001, 1000)
    assert torch.allclose(objectives.shift_sigmas(u, 5.0), s.sigmas[:1000], atol=1e-6)
    assert torch.allclose(objectives.unshift_sigmas(objectives.shift_sigmas(u, 5.0), 5.0), u, atol=1e-6)
    x = torch.randn(4, 16, 2, 4, 4)
    g = torch.Generator().manual_seed(3)
    sig = objectives.flow_sigmas(4, objectives.FlowSettings(shift=5.0), generator=g)
    noisy, target, t = objectives.flow_inputs(x, sig, generator=torch.Generator().manual_seed(4))
    noise = target + x
    sv = sig.view(-1, 1, 1, 1, 1)
    assert torch.allclose(noisy, (1 - sv) * x + sv * noise, atol=1e-6)
    assert torch.allclose(t, sig * 1000)


@pytest.mark.parametrize("sampling", ["uniform", "logit_normal", "mode"])
def test_sigma_ranges_restrict_training_to_one_expert(sampling: str) -> None:
    settings = objectives.FlowSettings(shift=12.0, sampling=sampling)
    g = torch.Generator().manual_seed(5)
    high = objectives.flow_sigmas(512, settings, sigma_range=(0.875, 1.0), generator=g)
    low = objectives.flow_sigmas(512, settings, sigma_range=(0.0, 0.875), generator=g)
    assert (high >= 0.875 - 1e-6).all() and (low < 0.875 + 1e-6).all()
    both = objectives.flow_sigmas(4096, settings, generator=g)
    # shift 12 puts most of the mass at high noise, as Wan2.2 A14B sampling does
    assert (both > 0.875).float().mean() > 0.4
    with pytest.raises(ValueError, match="sampling"):
        objectives.FlowSettings(sampling="cosine")
