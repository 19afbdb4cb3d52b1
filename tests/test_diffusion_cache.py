"""The latent + text cache: posterior mean and std stored (fresh samples each draw), reuse, stale
caches refused with every difference named, killed builds never look finished. Real tiny VAE."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")


from morphgs import MorphgsError  # noqa: E402
from morphgs.diffusion import LatentCacheError  # noqa: E402
from morphgs.diffusion import tiny as td  # noqa: E402
from morphgs.diffusion.codecs import LatentNorm, SDCodec, WanCodec, files_fingerprint  # noqa: E402
from morphgs.diffusion.latent_cache import CacheKey, CacheSource, LatentCache, build_cache  # noqa: E402


@pytest.fixture(scope="module")
def codec(tmp_path_factory: pytest.TempPathFactory) -> SDCodec:
    from diffusers import AutoencoderKL

    root = td.sd15_folder(tmp_path_factory.mktemp("vae") / "sd15")
    return SDCodec(AutoencoderKL.from_pretrained(root / "vae", local_files_only=True))


def _key(**kw) -> CacheKey:
    base = dict(model="sandbox", vae="AutoencoderKL:abc", text_encoder="CLIPTextModel:def", height=32, width=32,
                frames=3, stride=3, dtype="float32", dataset="d0", split="train", prompts="p0", text_tokens=16)
    return CacheKey(**{**base, **kw})


def _sources(n: int = 3, seed: int = 0) -> list[CacheSource]:
    g = torch.Generator().manual_seed(seed)
    return [CacheSource(pair_id=f"pair{i // 2}", start=3 * (i % 2), clean=torch.rand(3, 3, 32, 32, generator=g) * 2 - 1,
                        corrupted=torch.rand(3, 3, 32, 32, generator=g) * 2 - 1,
                        prompt="remove degradation" if i else "a caption") for i in range(n)]


def _text(prompts):
    return torch.stack([torch.full((4, 8), float(len(p))) for p in prompts])


def test_cache_stores_the_posterior_mean_and_std_and_each_draw_is_fresh(codec: SDCodec, tmp_path: Path) -> None:
    srcs = _sources()
    cache = build_cache(tmp_path / "c", _key(), srcs, posterior=codec.posterior, encode_text=_text)
    assert len(cache) == 3 and cache.prompts == ["a caption", "remove degradation"]
    item = cache.load(1)
    mean, std = codec.posterior(srcs[1].clean.unsqueeze(0))
    assert torch.equal(item["clean_mean"], mean[0]) and torch.equal(item["clean_std"], std[0])
    mean_c, std_c = codec.posterior(srcs[1].corrupted.unsqueeze(0))
    assert torch.equal(item["corrupted_mean"], mean_c[0]) and torch.equal(item["corrupted_std"], std_c[0])
    assert item["clean_mean"].shape == (4, 3, 4, 4)  # (C, F, H/8, W/8)
    assert torch.equal(item["text"], torch.full((4, 8), float(len("remove degradation"))))
    assert (item["pair_id"], item["start"]) == ("pair0", 3)
    # the std is the VAE's (a narrow posterior, like a trained VAE's), so samples differ but stay close
    assert 0 < item["clean_std"].mean() < 0.05
    draws = [item["clean_mean"] + item["clean_std"] * torch.randn_like(item["clean_std"]) for _ in range(2)]
    assert not torch.equal(draws[0], draws[1])
    assert torch.allclose(draws[0], item["clean_mean"], atol=0.1)


def test_a_matching_cache_is_reused_without_encoding(codec: SDCodec, tmp_path: Path) -> None:
    build_cache(tmp_path / "c", _key(), _sources(), posterior=codec.posterior, encode_text=_text)

    def refuse(*_a):
        raise AssertionError("the cache was encoded again")

    again = build_cache(tmp_path / "c", _key(), iter(()), posterior=refuse, encode_text=refuse)
    assert len(again) == 3


def test_a_stale_cache_is_refused_naming_every_difference(codec: SDCodec, tmp_path: Path) -> None:
    root = tmp_path / "c"
    build_cache(root, _key(), _sources(), posterior=codec.posterior, encode_text=_text)
    with pytest.raises(LatentCacheError) as e:
        LatentCache.open(root, _key(vae="AutoencoderKL:other", frames=5, dataset="d1"))
    msg = str(e.value)
    assert str(root) in msg and "vae:" in msg and "frames: cache has 3, this run wants 5" in msg and "dataset:" in msg
    assert "height" not in msg and isinstance(e.value, MorphgsError)
    with pytest.raises(LatentCacheError, match="stale"):
        build_cache(root, _key(height=64), _sources(), posterior=codec.posterior, encode_text=_text)
    # rebuild re-encodes for the new key
    rebuilt = build_cache(root, _key(prompts="p1"), _sources(2), posterior=codec.posterior, encode_text=_text,
                          rebuild=True)
    assert len(rebuilt) == 2 and LatentCache.open(root, _key(prompts="p1")) is not None


def test_a_killed_build_leaves_no_cache_behind(codec: SDCodec, tmp_path: Path) -> None:
    calls = []

    def dies(clip):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return codec.posterior(clip)

    with pytest.raises(KeyboardInterrupt):
        build_cache(tmp_path / "c", _key(), _sources(), posterior=dies, encode_text=_text)
    assert not (tmp_path / "c").exists() and not list(tmp_path.iterdir())
    # a folder of something else is not taken for a cache
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.txt").write_text("x")
    with pytest.raises(LatentCacheError, match="not a morphgs latent cache"):
        LatentCache.open(tmp_path / "junk", _key())


def test_a_damaged_item_is_named(codec: SDCodec, tmp_path: Path) -> None:
    cache = build_cache(tmp_path / "c", _key(), _sources(), posterior=codec.posterior, encode_text=_text)
    (tmp_path / "c" / "items" / "000001.safetensors").write_bytes(b"truncated")
    with pytest.raises(LatentCacheError, match="000001.safetensors"):
        cache.load(1)


def test_storage_dtype_is_part_of_the_key(codec: SDCodec, tmp_path: Path) -> None:
    key = _key(dtype="bfloat16")
    cache = build_cache(tmp_path / "c", key, _sources(1), posterior=codec.posterior, encode_text=_text)
    item = cache.load(0)
    assert item["clean_mean"].dtype == torch.float32  # read back as float32
    with pytest.raises(LatentCacheError, match="dtype"):
        LatentCache.open(tmp_path / "c", dataclasses.replace(key, dtype="float32"))
    with pytest.raises(ValueError, match="dtype"):
        _key(dtype="int8")


def test_latent_scaling_follows_the_vae_configs(codec: SDCodec, tmp_path: Path) -> None:
    sd = LatentNorm.from_vae_config(codec.vae.config)
    z = torch.randn(1, 4, 2, 3, 3)
    assert torch.allclose(sd.normalize(z), z * 0.18215) and torch.allclose(sd.denormalize(sd.normalize(z)), z)
    from diffusers import AutoencoderKLWan

    wan_root = td.wan_folder(tmp_path / "wan", experts=1)
    vae = AutoencoderKLWan.from_pretrained(wan_root / "vae", local_files_only=True)
    wn = WanCodec(vae)
    z = torch.randn(1, 16, 2, 3, 3)
    mean = torch.tensor(vae.config.latents_mean).view(1, -1, 1, 1, 1)
    std = torch.tensor(vae.config.latents_std).view(1, -1, 1, 1, 1)
    assert torch.allclose(wn.normalize(z), (z - mean) / std, atol=1e-5)
    with pytest.raises(ValueError, match="4k\\+1"):
        wn.check_clip(8, 32, 32)
    # component fingerprints follow the files, not their paths
    assert files_fingerprint(wan_root / "vae") != files_fingerprint(wan_root / "text_encoder")
