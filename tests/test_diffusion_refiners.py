"""The refiners as Python objects (no CLI): per-pair captions in the cache, the Wan2.2 A14B expert
routing, one-expert training, TI2V-5B end to end, and the cached dataset's keys through a real
DataLoader worker. Tiny random models (morphgs.diffusion.tiny), a real curated folder."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from morphgs import MorphgsError, cli  # noqa: E402
from morphgs.data import PairDataset  # noqa: E402
from morphgs.diffusion import tiny  # noqa: E402
from morphgs.models import ModelContext, create_model  # noqa: E402


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("refiners")
    data = root / "data"
    assert cli.main(["curate", "--out", str(data), "--frames", "5", "--size", "32x32", "-k", "1",
                     "--sample-gaussians", "3000", "--test-fraction", "0", "--no-progress"]) == 0
    return {"root": root, "data": data, "wan": tiny.wan_folder(root / "wan"),
            "ti2v": tiny.wan_folder(root / "ti2v", experts=1, ti2v=True)}


def _controlnet(world: dict[str, Path], tmp_path: Path, *, folder: str = "wan", training: bool = True, **extra):
    ctx = ModelContext(frames=5, size=(32, 32), training=training, cache_dir=tmp_path / "cache")
    table = {"wan": str(world[folder]), "controlnet_blocks": 3, "text_tokens": tiny.TOKENS, "weight_dtype": "float32",
             "gradient_checkpointing": False, "inference_steps": 3, **extra}
    torch.manual_seed(0)
    return create_model("controlnet", table, ctx), ctx


def _dataset(world: dict[str, Path]) -> PairDataset:
    return PairDataset(world["data"], "train", 5, (32, 32), train=True)


def test_per_pair_captions_are_encoded_once_into_the_cache(world: dict[str, Path], tmp_path: Path) -> None:
    captions = tmp_path / "captions.jsonl"
    captions.write_text(json.dumps({"pair_id": "sample-1/morphological/0000", "caption": "a blurry orbit"}) + "\n")
    model, ctx = _controlnet(world, tmp_path, captions=str(captions))
    ds = model.prepare_data(_dataset(world), ctx=ctx)
    cache = ds.cache
    assert sorted(cache.prompts) == ["a blurry orbit", "remove degradation"]
    by_pair = {it["pair_id"]: cache.prompts[it["text"]] for it in cache.items}
    assert by_pair == {"sample-0/morphological/0000": "remove degradation",
                       "sample-1/morphological/0000": "a blurry orbit"}
    assert not torch.equal(cache.text[0], cache.text[1])
    assert "text" not in model._aux  # the text encoder is dropped once the prompts are cached
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"pair_id": "x"}\n')
    model2, ctx2 = _controlnet(world, tmp_path / "2", captions=str(bad))
    with pytest.raises(MorphgsError, match="bad.jsonl line 1"):
        model2.prepare_data(_dataset(world), ctx=ctx2)


def test_each_sample_runs_the_expert_of_its_noise_level(world: dict[str, Path], tmp_path: Path) -> None:
    model, ctx = _controlnet(world, tmp_path)
    assert len(model.experts) == 2 and model.boundary_ratio == 0.875
    ds = model.prepare_data(_dataset(world), ctx=ctx)
    batch = torch.utils.data.default_collate([ds[(0, 1)], ds[(1, 2)]])
    calls = [0, 0]
    hooks = [e.blocks[0].register_forward_hook(lambda *_a, i=i: calls.__setitem__(i, calls[i] + 1))
             for i, e in enumerate(model.experts)]
    gen = torch.Generator().manual_seed(0)
    sigmas = []
    for _ in range(6):
        loss, logs = model(batch, generator=gen)
        loss.backward()
        sigmas.append(float(logs["sigma"]))
    for h in hooks:
        h.remove()
    assert calls[0] > 0 and calls[1] > 0  # both experts ran, each on its own samples
    assert all(p.grad is None for e in model.experts for p in e.parameters())


def test_training_one_expert_loads_only_that_expert(world: dict[str, Path], tmp_path: Path) -> None:
    from morphgs.diffusion import objectives

    low, _ = _controlnet(world, tmp_path, train_experts="low", controlnet_source="transformer")
    assert len(low.experts) == 1 and low.expert_names == ["transformer_2"]
    # the blocks still come from the named source expert (loaded for the copy, then dropped)
    full, _ = _controlnet(world, tmp_path / "full")
    assert torch.equal(low.controlnet.blocks[1].attn1.to_q.weight, full.experts[0].blocks[3].attn1.to_q.weight)
    g = torch.Generator().manual_seed(0)
    s = objectives.flow_sigmas(256, low.flow, sigma_range=low._sigma_range, generator=g)
    assert float(s.max()) <= 0.875 + 1e-6
    inference, _ = _controlnet(world, tmp_path / "inf", training=False, train_experts="low")
    assert len(inference.experts) == 2  # refine needs both


def test_ti2v_5b_layout_trains_and_refines(world: dict[str, Path], tmp_path: Path) -> None:
    model, ctx = _controlnet(world, tmp_path, folder="ti2v")
    assert model.expand_timesteps and model.boundary_ratio is None and model.size_multiple == 32
    ds = model.prepare_data(_dataset(world), ctx=ctx)
    assert ds.cache.meta["latent_shape"] == [48, 2, 2, 2]  # Wan2.2 VAE: 48 channels, 16x spatial
    opt = torch.optim.AdamW(model.param_groups(lr=1e-3, weight_decay=0.0))
    batch = torch.utils.data.default_collate([ds[(0, 0)]])
    before = model.controlnet.proj_out[0].weight.detach().clone()
    loss, _ = model(batch, generator=torch.Generator().manual_seed(0))
    loss.backward()
    opt.step()
    assert torch.isfinite(loss) and not torch.equal(model.controlnet.proj_out[0].weight, before)
    model.eval()
    out = model.refine(torch.zeros(1, 3, 5, 32, 32), generator=torch.Generator().manual_seed(0))
    assert out.shape == (1, 3, 5, 32, 32) and torch.isfinite(out).all() and out.abs().max() <= 1


def test_cached_pairs_keep_the_datasets_keys_through_a_worker(world: dict[str, Path], tmp_path: Path) -> None:
    from morphgs.data import sample_seed

    model, ctx = _controlnet(world, tmp_path, cache_stride=1)
    pixels = _dataset(world)
    ds = model.prepare_data(pixels, ctx=ctx)
    assert len(ds) == len(pixels) == 2
    assert len(ds.cache) == 2  # 5-frame pairs, 5-frame windows: one window each, at any stride
    keys = [(i, sample_seed(0, 0, i)) for i in range(2)]
    loader = torch.utils.data.DataLoader([ds[k] for k in keys], batch_size=2)  # the same items, collated
    direct = next(iter(loader))
    worker = next(iter(torch.utils.data.DataLoader(_Keyed(ds, keys), batch_size=2, num_workers=1)))
    assert worker["pair_id"] == direct["pair_id"] == [r.pair_id for r in pixels.records]
    assert all(torch.equal(worker[k], direct[k]) for k in ("clean_mean", "clean_std", "corrupted_mean", "text"))


class _Keyed(torch.utils.data.Dataset):  # type: ignore[type-arg]
    def __init__(self, ds, keys):
        self.ds, self.keys = ds, keys

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, i: int):
        return self.ds[self.keys[i]]
