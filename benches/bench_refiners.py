"""The two diffusion refiners on a CPU: training steps/s of the tiny configs, latent-cache build
rate, and the parameter counts and memory estimates of the real-size models.

1. Tiny random models (morphgs.diffusion.tiny, the test suite's) on a curated folder of 2 pairs
   (5 frames, 32x32): latent-cache build (windows/s, VAE posterior of clean + corrupted and the
   prompt), then timed training steps (forward + backward + AdamW, batch 1) at --threads torch
   threads, after 3 warm-up steps.
2. The real architectures built on the meta device (no memory, no weights): SD 1.5 UNet +
   AnimateDiff v1.5.2 motion modules with LoRA r64 + conv_in 8; Wan2.2 T2V-A14B expert and
   TI2V-5B with the 8-block dilated ControlNet. Parameter counts are exact; the memory figures
   are estimates (see docs/refiners.md, "Memory").

    python benches/bench_refiners.py              # about a minute on 2 cores
    python benches/bench_refiners.py --steps 5    # smoke check
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch  # noqa: E402

GB = 1e9


def _curate(out: Path) -> None:
    subprocess.run([sys.executable, "-m", "morphgs", "curate", "--out", str(out), "--frames", "5", "--size", "32x32",
                    "-k", "1", "--sample-gaussians", "3000", "--test-fraction", "0", "--no-progress"],
                   check=True, capture_output=True)


def _tiny(work: Path, steps: int) -> list[dict[str, Any]]:
    from morphgs.data import PairDataset
    from morphgs.diffusion import tiny
    from morphgs.models import ModelContext, create_model

    models = {"sd15": tiny.sd15_folder(work / "sd15"), "motion": tiny.motion_adapter_folder(work / "motion"),
              "wan": tiny.wan_folder(work / "wan")}
    data = work / "data"
    _curate(data)
    cases = {
        "sandbox": ({"sd15": str(models["sd15"]), "motion_adapter": str(models["motion"]), "lora_rank": 8,
                     "lora_alpha": 16.0}, 4),
        "controlnet": ({"wan": str(models["wan"]), "controlnet_blocks": 3, "text_tokens": tiny.TOKENS}, 5),
    }
    rows = []
    for name, (table, frames) in cases.items():
        table = {**table, "weight_dtype": "float32", "gradient_checkpointing": False,
                 "cache_dir": str(work / "cache")}
        ctx = ModelContext(frames=frames, size=(32, 32), training=True, cache_dir=work / "cache")
        torch.manual_seed(0)
        model = create_model(name, table, ctx)
        ds = PairDataset(data, "train", frames, (32, 32), train=True)
        t0 = time.perf_counter()
        latents = model.prepare_data(ds, ctx=ctx, accelerator=None)
        t_cache = time.perf_counter() - t0
        windows = len(latents.cache)
        batch = {k: v[None] for k, v in latents[(0, 0)].items() if torch.is_tensor(v)}
        opt = torch.optim.AdamW(model.param_groups(lr=1e-4, weight_decay=1e-2))
        model.train()
        gen = torch.Generator().manual_seed(0)
        times = []
        for i in range(steps + 3):
            t0 = time.perf_counter()
            loss, _ = model(batch, generator=gen)
            loss.backward()
            opt.step()
            opt.zero_grad(set_to_none=True)
            if i >= 3:
                times.append(time.perf_counter() - t0)
        trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
        rows.append({"model": name, "frames": frames, "trainable": trainable, "windows": windows,
                     "cache_s": t_cache, "steps_per_s": len(times) / sum(times)})
    return rows


def _real_vae_rates() -> list[tuple[str, float]]:
    """Encode rate (frames/s) of the real VAE architectures (random weights) at training sizes."""
    from diffusers import AutoencoderKL, AutoencoderKLWan

    from morphgs.diffusion.codecs import SDCodec, WanCodec

    torch.manual_seed(0)
    sd = AutoencoderKL(block_out_channels=(128, 256, 512, 512), down_block_types=("DownEncoderBlock2D",) * 4,
                       up_block_types=("UpDecoderBlock2D",) * 4, layers_per_block=2, latent_channels=4).eval()
    out = []
    x = torch.rand(1, 3, 2, 384, 640) * 2 - 1
    t0 = time.perf_counter()
    SDCodec(sd, chunk=2).posterior(x)
    out.append(("SD 1.5 VAE, 384x640 frames", 2 / (time.perf_counter() - t0)))
    x = torch.rand(1, 3, 5, 240, 416) * 2 - 1
    t0 = time.perf_counter()
    WanCodec(AutoencoderKLWan().eval()).posterior(x)  # the Wan2.1 VAE (Wan2.2 A14B's)
    out.append(("Wan2.1 VAE, 5 frames of 240x416", 5 / (time.perf_counter() - t0)))
    return out


def _sandbox_real() -> dict[str, float]:
    from diffusers import MotionAdapter, UNet2DConditionModel, UNetMotionModel

    from morphgs.diffusion.sandbox import add_lora, count_lora_parameters, widen_conv_in

    with torch.device("meta"):
        unet = UNet2DConditionModel(cross_attention_dim=768, attention_head_dim=8, sample_size=64)  # SD 1.5
        adapter = MotionAdapter(block_out_channels=(320, 640, 1280, 1280), motion_layers_per_block=2,
                                motion_num_attention_heads=8, motion_max_seq_length=32, use_motion_mid_block=True)
        model = UNetMotionModel.from_unet2d(unet, adapter, load_weights=False)
        widen_conv_in(model, in_channels=8)
        lora = count_lora_parameters(model, rank=64)
        add_lora(model, rank=64, alpha=128, dropout=0.05)
    total = sum(p.numel() for p in model.parameters())
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    return {"frozen": total - trainable, "trainable": trainable, "lora": lora}


def _wan_real(kind: str) -> dict[str, float]:
    from diffusers import WanTransformer3DModel

    from morphgs.diffusion.controlnet import DilatedControlNet

    if kind == "A14B":  # one expert of Wan2.2 T2V-A14B (the model holds two)
        cfg = dict(num_attention_heads=40, attention_head_dim=128, in_channels=16, out_channels=16, text_dim=4096,
                   ffn_dim=13824, num_layers=40)
    else:  # Wan2.2 TI2V-5B
        cfg = dict(num_attention_heads=24, attention_head_dim=128, in_channels=48, out_channels=48, text_dim=4096,
                   ffn_dim=14336, num_layers=30)
    with torch.device("meta"):
        base = WanTransformer3DModel(**cfg)
        net = DilatedControlNet.from_transformer(base, num_blocks=8, stride=3)
    return {"expert": sum(p.numel() for p in base.parameters()), "controlnet": sum(p.numel() for p in net.parameters()),
            "dim": cfg["num_attention_heads"] * cfg["attention_head_dim"], "layers": cfg["num_layers"],
            "ffn": cfg["ffn_dim"]}


def _wan_memory(p: dict[str, float], *, experts: int, tokens: int, gpus: int, mode: str) -> dict[str, float]:
    """GB per GPU (estimate).

    base: the frozen experts in bf16 (2 B/parameter), whole on each GPU, or sharded with FSDP.
    trainable: the ControlNet: one GPU holds fp32 weights, fp32 gradients and AdamW's two moments
    (16 B/parameter); ZeRO-2 keeps bf16 weights on every GPU (2 B) and shards fp32 master weights,
    moments and bf16 gradients (14 B / GPUs); FSDP shards all 16 B.
    activations: with block checkpointing, each block's bf16 input (tokens x dim) is kept for the
    base blocks and the ControlNet's, plus one block's recomputation at a time (q, k, v, attention
    output and projections ~6 x dim, FFN hidden 2 x ffn, bf16).
    """
    base = 2 * p["expert"] * experts / (gpus if mode == "fsdp" else 1) / GB
    c = p["controlnet"]
    train = {"single": 16 * c, "zero2": 2 * c + 14 * c / gpus, "fsdp": 16 * c / gpus}[mode] / GB
    blocks = p["layers"] + 8
    act = (blocks * tokens * p["dim"] * 2 + tokens * (6 * p["dim"] + 2 * p["ffn"]) * 2) / GB
    return {"base": base, "trainable": train, "activations": act, "total": base + train + act}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=30, help="timed training steps per model")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (2 = the target machine)")
    ap.add_argument("--real-vae", action="store_true", help="also time the real VAE architectures (slow on CPUs)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    work = Path(tempfile.mkdtemp(prefix="morphgs-bench-refiners-"))
    try:
        load = os.getloadavg()[0]
        print(f"tiny configs, {args.threads} torch thread(s), batch 1, 32x32 clips "
              f"(load average {load:.1f} on {os.cpu_count()} CPUs):")
        for r in _tiny(work, args.steps):
            print(f"  {r['model']:<10} {r['frames']} frames  {r['trainable']:>8,} trainable  "
                  f"{r['steps_per_s']:6.1f} steps/s  cache {r['windows']} windows in {r['cache_s']:.2f} s "
                  f"({r['windows'] / r['cache_s']:.1f} windows/s)")
    finally:
        shutil.rmtree(work, ignore_errors=True)

    if args.real_vae:
        print("\nreal VAE architectures (random weights), posterior encode on the CPU:")
        for label, rate in _real_vae_rates():
            print(f"  {label}: {rate:.3f} frames/s")

    sb = _sandbox_real()
    print("\nreal sizes (meta device; counts exact):")
    print(f"  sandbox: motion UNet {sb['frozen'] / 1e9:.3f} B frozen, {sb['trainable'] / 1e6:.1f} M trainable "
          f"(LoRA r64 {sb['lora'] / 1e6:.1f} M + conv_in)")
    for kind in ("A14B", "TI2V-5B"):
        p = _wan_real(kind)
        print(f"  controlnet on {kind}: expert {p['expert'] / 1e9:.2f} B, ControlNet {p['controlnet'] / 1e9:.2f} B "
              f"(dim {p['dim']}, {p['layers']} base blocks)")
        # 49 frames 480x832: Wan2.1 VAE (A14B) 13x60x104 latents -> 13x30x52 tokens; Wan2.2 VAE (5B) 16x -> 13x15x26
        tokens = 13 * 30 * 52 if kind == "A14B" else 13 * 15 * 26
        experts = 2 if kind == "A14B" else 1
        setups = [("1 GPU", 1, "single", experts), ("8 GPUs ZeRO-2", 8, "zero2", experts),
                  ("8 GPUs FSDP", 8, "fsdp", experts)]
        if experts == 2:
            setups.insert(2, ("8 GPUs ZeRO-2", 8, "zero2", 1))  # train_experts = "high" / "low"
        for label, gpus, mode, n in setups:
            m = _wan_memory(p, experts=n, tokens=tokens, gpus=gpus, mode=mode)
            print(f"    {label:<14} {n} expert(s) loaded: base {m['base']:5.1f} + trainable {m['trainable']:5.1f} + "
                  f"activations {m['activations']:4.1f} = {m['total']:5.1f} GB per GPU (estimate)")


if __name__ == "__main__":
    main()
