"""Tiny random SD 1.5 / AnimateDiff / Wan model folders in the real diffusers layouts.

For tests, benchmarks and smoke runs without downloaded weights: each function builds a model
with a fixed seed and `save_pretrained`s it, so the refiners' real local-folder loading path runs
(no hub). Shapes follow the diffusers test suites' tiny configs
(tests/models/unets/test_models_unet_motion.py, tests/pipelines/wan/test_wan_22.py) with a few
channels more where group norms need them. The VAEs get a trained VAE's narrow posterior.

```python
from morphgs.diffusion import tiny
tiny.sd15_folder(Path("m/sd15")); tiny.motion_adapter_folder(Path("m/motion")); tiny.wan_folder(Path("m/wan"))
```
"""

from __future__ import annotations

import json
import string
from pathlib import Path
from typing import Any

import torch

__all__ = ["TEXT_DIM", "TOKENS", "motion_adapter_folder", "sd15_folder", "wan_folder"]

TEXT_DIM = 16
TOKENS = 16


def clip_tokenizer() -> Any:
    """A CLIP BPE tokenizer over single letters."""
    from transformers import CLIPTokenizer

    chars = string.ascii_lowercase
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in chars:
        vocab[c] = len(vocab)
    for c in chars:
        vocab[c + "</w>"] = len(vocab)
    return CLIPTokenizer(vocab=vocab, merges=[], model_max_length=TOKENS)


def t5_tokenizer() -> Any:
    """A T5 (Unigram) tokenizer over single letters."""
    from transformers import T5Tokenizer

    vocab = [("<pad>", 0.0), ("</s>", 0.0), ("<unk>", 0.0), ("\u2581", -2.0)]
    vocab += [(c, -3.0) for c in string.ascii_lowercase]
    return T5Tokenizer(vocab=vocab, extra_ids=0, model_max_length=TOKENS)


def _narrow_posterior(quant_conv: torch.nn.Module, latent_channels: int) -> None:
    """Give a random VAE a trained VAE's narrow posterior (std around 0.002 instead of 1): the
    log-variance rows of quant_conv get small weights and a bias of -12."""
    conv: Any = quant_conv
    with torch.no_grad():
        conv.weight[latent_channels:] *= 0.01
        conv.bias[latent_channels:] = -12.0


def sd15_folder(root: Path, *, seed: int = 0) -> Path:
    """A tiny SD 1.5-shaped model folder: unet/, vae/ (8x downsampling), text_encoder/, tokenizer/,
    scheduler/ and model_index.json (so it also serves as the config folder of a single file)."""
    from diffusers import AutoencoderKL, PNDMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(seed)
    unet: Any = UNet2DConditionModel(
        block_out_channels=(16, 32), layers_per_block=1, sample_size=8, in_channels=4, out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=TEXT_DIM, norm_num_groups=8, attention_head_dim=4,
    )
    unet.save_pretrained(root / "unet")
    vae: Any = AutoencoderKL(
        block_out_channels=(8, 8, 8, 8), down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4, latent_channels=4, norm_num_groups=4, layers_per_block=1,
        sample_size=32,
    )
    _narrow_posterior(vae.quant_conv, 4)
    vae.save_pretrained(root / "vae")
    CLIPTextModel(CLIPTextConfig(
        hidden_size=TEXT_DIM, intermediate_size=37, num_attention_heads=4, num_hidden_layers=2, vocab_size=64,
        max_position_embeddings=TOKENS, bos_token_id=0, eos_token_id=1, pad_token_id=1,
    )).save_pretrained(root / "text_encoder")
    clip_tokenizer().save_pretrained(root / "tokenizer")
    scheduler: Any = PNDMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                                   skip_prk_steps=True, steps_offset=1, set_alpha_to_one=False)
    scheduler.save_pretrained(root / "scheduler")
    index = {"_class_name": "StableDiffusionPipeline", "requires_safety_checker": False,
             "feature_extractor": [None, None], "safety_checker": [None, None],
             "scheduler": ["diffusers", "PNDMScheduler"], "text_encoder": ["transformers", "CLIPTextModel"],
             "tokenizer": ["transformers", "CLIPTokenizer"], "unet": ["diffusers", "UNet2DConditionModel"],
             "vae": ["diffusers", "AutoencoderKL"]}
    (root / "model_index.json").write_text(json.dumps(index))
    return root


def motion_adapter_folder(root: Path, *, seed: int = 1) -> Path:
    """A tiny AnimateDiff motion adapter matching `sd15_folder`'s UNet."""
    from diffusers import MotionAdapter

    torch.manual_seed(seed)
    adapter: Any = MotionAdapter(block_out_channels=(16, 32), motion_layers_per_block=1, motion_norm_num_groups=8,
                                 motion_num_attention_heads=2, motion_max_seq_length=32)
    adapter.save_pretrained(root)
    return root


def wan_transformer_kwargs(*, channels: int = 16, layers: int = 8) -> dict[str, Any]:
    """A tiny WanTransformer3DModel config (8 blocks: a 3-block ControlNet at stride 3 fits)."""
    return dict(patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=32, in_channels=channels,
                out_channels=channels, text_dim=TEXT_DIM, freq_dim=32, ffn_dim=64, num_layers=layers,
                cross_attn_norm=True, qk_norm="rms_norm_across_heads", rope_max_seq_len=32)


def wan_folder(root: Path, *, experts: int = 2, boundary_ratio: float = 0.875, ti2v: bool = False,
               seed: int = 2) -> Path:
    """A tiny Wan2.2-shaped folder: A14B-style (two experts + boundary_ratio) by default, or
    TI2V-5B-style (one expert, 48-channel Wan2.2 VAE with 16x spatial factor, expand_timesteps)."""
    from diffusers import AutoencoderKLWan, WanTransformer3DModel
    from transformers import UMT5Config, UMT5EncoderModel

    torch.manual_seed(seed)
    channels = 48 if ti2v else 16
    names = ["transformer", "transformer_2"][:experts]
    for name in names:
        transformer: Any = WanTransformer3DModel(**wan_transformer_kwargs(channels=channels))
        transformer.save_pretrained(root / name)
    vae: Any
    if ti2v:
        vae = AutoencoderKLWan(base_dim=3, z_dim=48, in_channels=12, out_channels=12, is_residual=True, patch_size=2,
                               latents_mean=[0.0] * 48, latents_std=[1.0] * 48, dim_mult=[1, 1, 1, 1],
                               num_res_blocks=1, scale_factor_spatial=16, scale_factor_temporal=4,
                               temperal_downsample=[False, True, True])
    else:
        vae = AutoencoderKLWan(base_dim=3, z_dim=16, dim_mult=[1, 1, 1, 1], num_res_blocks=1,
                               temperal_downsample=[False, True, True])
    _narrow_posterior(vae.quant_conv, channels)
    vae.save_pretrained(root / "vae")
    UMT5EncoderModel(UMT5Config(d_model=TEXT_DIM, d_kv=4, d_ff=32, num_layers=2, num_heads=4, vocab_size=64,
                                relative_attention_num_buckets=8)).save_pretrained(root / "text_encoder")
    t5_tokenizer().save_pretrained(root / "tokenizer")
    index = {"_class_name": "WanPipeline", "boundary_ratio": boundary_ratio if experts == 2 else None,
             "expand_timesteps": ti2v}
    (root / "model_index.json").write_text(json.dumps(index))
    return root
