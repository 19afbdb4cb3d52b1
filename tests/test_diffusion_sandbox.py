"""The sandbox network (SD 1.5 UNet + AnimateDiff): local loading, conv_in surgery, LoRA placement,
the DDPM objective. Tiny random models saved in diffusers layout (tests/tiny_diffusion.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("peft")


from morphgs import MorphgsError  # noqa: E402
from morphgs.diffusion import ModelFolderError  # noqa: E402
from morphgs.diffusion import tiny as td  # noqa: E402
from morphgs.diffusion import objectives, sandbox  # noqa: E402


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sandbox-models")
    return {"sd": td.sd15_folder(root / "sd15"), "adapter": td.motion_adapter_folder(root / "motion")}


@pytest.fixture(scope="module")
def parts(folders: dict[str, Path]):
    return sandbox.load_sd15(folders["sd"]), sandbox.load_motion_adapter(folders["adapter"])


def _motion_unet(parts, **kw):
    from diffusers import UNetMotionModel

    sd, adapter = parts
    return UNetMotionModel.from_unet2d(sd.unet, adapter) if not kw else sandbox.build_motion_unet(sd.unet, adapter, **kw)


def test_conv_in_widening_is_exact_and_round_trips(parts, tmp_path: Path) -> None:
    from diffusers import UNetMotionModel

    unet = _motion_unet(parts)
    w0, b0 = unet.conv_in.weight.detach().clone(), unet.conv_in.bias.detach().clone()
    sandbox.widen_conv_in(unet, in_channels=8, cond_scale=0.1)
    w, b = unet.conv_in.weight.detach(), unet.conv_in.bias.detach()
    assert w.shape == (w0.shape[0], 8, *w0.shape[2:])
    assert torch.equal(w[:, :4], w0)
    assert torch.equal(w[:, 4:], 0.1 * w0)
    assert torch.equal(b, b0)
    assert unet.config.in_channels == 8
    unet.save_pretrained(tmp_path / "widened")
    assert json.loads((tmp_path / "widened" / "config.json").read_text())["in_channels"] == 8
    back = UNetMotionModel.from_pretrained(tmp_path / "widened", local_files_only=True)
    assert back.conv_in.in_channels == 8
    assert torch.equal(back.conv_in.weight, w) and torch.equal(back.conv_in.bias, b)


def test_widening_by_a_non_multiple_is_refused(parts) -> None:
    with pytest.raises(ValueError, match="multiple"):
        sandbox.widen_conv_in(_motion_unet(parts), in_channels=6)


def test_trainable_parameters_are_exactly_lora_plus_conv_in(parts) -> None:
    rank = 4
    unet = _motion_unet(parts, lora_rank=rank, lora_alpha=2 * rank)
    trainable = {n: p for n, p in unet.named_parameters() if p.requires_grad}
    lora = {n for n in trainable if ".lora_A." in n or ".lora_B." in n}
    assert set(trainable) == lora | {"conv_in.weight", "conv_in.bias"}
    expected = sandbox.count_lora_parameters(unet, rank=rank) + unet.conv_in.weight.numel() + unet.conv_in.bias.numel()
    assert sum(p.numel() for p in trainable.values()) == expected
    # and that count is what LoRA on every attention projection of the model must add
    n_targets = sum(1 for name, _ in unet.named_modules() if name.endswith((".to_q", ".to_k", ".to_v", ".to_out.0")))
    assert n_targets > 0 and len(lora) == 2 * n_targets
    assert sandbox.trainable_state_dict(unet).keys() == trainable.keys()


def test_lora_sits_on_spatial_and_motion_attention(parts) -> None:
    from peft.tuners.lora import LoraLayer

    unet = _motion_unet(parts, lora_rank=4, lora_alpha=8)
    wrapped = {n for n, m in unet.named_modules() if isinstance(m, LoraLayer)}
    for kind in (".attentions.", ".motion_modules."):
        for proj in ("to_q", "to_k", "to_v", "to_out.0"):
            for attn in ("attn1", "attn2"):
                hits = [n for n in wrapped if kind in n and n.endswith(f"{attn}.{proj}")]
                assert hits, f"no LoRA on {kind} {attn}.{proj}"
    # nothing else is wrapped (feed-forwards, resnets and projections stay plain)
    assert all(n.endswith(("to_q", "to_k", "to_v", "to_out.0")) for n in wrapped)
    lora_cfg = unet.peft_config["default"]
    assert (lora_cfg.r, lora_cfg.lora_alpha, lora_cfg.lora_dropout) == (4, 8, 0.05)


def test_lora_starts_as_the_identity_and_gradients_reach_only_trainables(parts) -> None:
    plain = _motion_unet(parts, lora_rank=0)
    lora = _motion_unet(parts, lora_rank=4, lora_alpha=8)
    lora.load_state_dict(plain.state_dict(), strict=False)  # same conv_in
    plain.eval(), lora.eval()
    x = torch.randn(1, 8, 3, 4, 4)
    text = torch.randn(3, td.TOKENS, td.TEXT_DIM)
    with torch.no_grad():
        assert torch.allclose(plain(x, 10, text).sample, lora(x, 10, text).sample, atol=1e-6)
    lora.train()
    lora(x, 10, text).sample.square().mean().backward()
    for n, p in lora.named_parameters():
        assert (p.grad is not None) == p.requires_grad, n


def test_paper_defaults_build_rank_64_alpha_128(parts) -> None:
    unet = _motion_unet(parts, lora_rank=64, lora_alpha=128, lora_dropout=0.05)
    cfg = unet.peft_config["default"]
    assert (cfg.r, cfg.lora_alpha, cfg.lora_dropout) == (64, 128, 0.05)
    assert set(cfg.target_modules) == {"to_q", "to_k", "to_v", "to_out.0"}


def test_missing_folders_and_parts_are_named(folders: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere"):
        sandbox.load_sd15(tmp_path / "nowhere")
    broken = shutil.copytree(folders["sd"], tmp_path / "sd")
    (broken / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    shutil.rmtree(broken / "tokenizer")
    with pytest.raises(ModelFolderError) as e:
        sandbox.load_sd15(broken)
    msg = str(e.value)
    assert str(broken) in msg and "unet/diffusion_pytorch_model.safetensors" in msg and "tokenizer/" in msg
    assert isinstance(e.value, MorphgsError) and isinstance(e.value, ValueError)
    empty = tmp_path / "adapter"
    empty.mkdir()
    with pytest.raises(ModelFolderError, match="config.json"):
        sandbox.load_motion_adapter(empty)


def test_single_file_checkpoint_needs_a_local_config_folder(tmp_path: Path) -> None:
    f = tmp_path / "v1-5-pruned.safetensors"
    f.write_bytes(b"not used")
    with pytest.raises(ModelFolderError, match="config folder"):
        sandbox.load_sd15(f)
    cfg = tmp_path / "cfg"
    (cfg / "unet").mkdir(parents=True)
    with pytest.raises(ModelFolderError, match="model_index.json"):
        sandbox.load_sd15(f, config_dir=cfg)


def test_original_single_file_sd15_checkpoint_loads(folders: dict[str, Path], parts, tmp_path: Path) -> None:
    """An original-layout (LDM) single-file SD 1.5 checkpoint loads through diffusers'
    from_single_file with a local config folder, to the same weights as the diffusers folder."""
    from ldm_checkpoint import sd15_to_ldm
    from safetensors.torch import save_file

    sd, _ = parts
    ckpt = tmp_path / "v1-5-tiny.safetensors"
    save_file(sd15_to_ldm(sd.unet, sd.vae, sd.text_encoder), str(ckpt))
    single = sandbox.load_sd15(ckpt, config_dir=folders["sd"])
    for name in ("unet", "vae", "text_encoder"):
        ref, got = getattr(sd, name).state_dict(), getattr(single, name).state_dict()
        assert got.keys() == ref.keys(), name
        assert all(torch.equal(got[k], ref[k]) for k in ref), name
    assert single.tokenizer("remove degradation").input_ids == sd.tokenizer("remove degradation").input_ids


def _to_original_motion_keys(state: dict) -> dict:
    """diffusers MotionAdapter keys -> the original AnimateDiff checkpoint's (the inverse of
    diffusers' convert_animatediff_checkpoint_to_diffusers)."""
    import re

    out = {}
    for k, v in state.items():
        k = re.sub(r"(motion_modules\.\d+)\.", r"\1.temporal_transformer.", k)
        k = (k.replace(".norm1", ".norms.0").replace(".norm2", ".norms.1").replace(".norm3", ".ff_norm")
             .replace(".attn1", ".attention_blocks.0").replace(".attn2", ".attention_blocks.1"))
        out[k] = v.contiguous()
    return out


def test_original_single_file_motion_module_loads(folders: dict[str, Path], parts, tmp_path: Path) -> None:
    from safetensors.torch import save_file

    _, adapter = parts
    ckpt = tmp_path / "mm_sd_v15_v2.safetensors"
    save_file(_to_original_motion_keys(adapter.state_dict()), str(ckpt))
    with pytest.raises(ModelFolderError, match="config folder"):
        sandbox.load_motion_adapter(ckpt)
    loaded = sandbox.load_motion_adapter(ckpt, config_dir=folders["adapter"])
    ref = adapter.state_dict()
    got = loaded.state_dict()
    assert got.keys() == ref.keys()
    assert all(torch.equal(got[k], ref[k]) for k in ref)


def test_adapter_that_does_not_fit_is_a_clear_error(parts, tmp_path: Path) -> None:
    from diffusers import MotionAdapter

    sd, _ = parts
    other = MotionAdapter(block_out_channels=(16, 32, 32), motion_layers_per_block=1, motion_norm_num_groups=8)
    with pytest.raises(ModelFolderError, match="does not fit"):
        sandbox.build_motion_unet(sd.unet, other)


def test_ddpm_schedule_is_sd15_scaled_linear_and_noising_is_exact() -> None:
    s = objectives.ddpm_scheduler()
    betas = torch.linspace(0.00085 ** 0.5, 0.012 ** 0.5, 1000, dtype=torch.float32) ** 2
    assert torch.allclose(s.betas, betas)
    assert s.config.prediction_type == "epsilon" and s.config.num_train_timesteps == 1000
    x = torch.randn(3, 4, 2, 4, 4)
    g = torch.Generator().manual_seed(0)
    noisy, target, t = objectives.ddpm_inputs(s, x, generator=g)
    ab = s.alphas_cumprod[t].view(-1, 1, 1, 1, 1)
    assert torch.allclose(noisy, ab.sqrt() * x + (1 - ab).sqrt() * target, atol=1e-6)
    assert t.dtype == torch.int64 and ((t >= 0) & (t < 1000)).all()
    # same generator state -> same draw; the next draw differs
    g2 = torch.Generator().manual_seed(0)
    assert torch.equal(objectives.ddpm_inputs(s, x, generator=g2)[0], noisy)
    assert not torch.equal(objectives.ddpm_inputs(s, x, generator=g2)[1], target)
