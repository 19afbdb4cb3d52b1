"""morphgs export webdataset: shards the real `webdataset` package reads back, with the right keys,
byte-identical members, counts per split, the shard size limits and a deterministic byte layout."""

from __future__ import annotations

import gc
import io
import json
import tarfile
import warnings
from pathlib import Path

import numpy as np
import pytest

from morphgs import exports, media
from morphgs.cli import main
from morphgs.curation import load_manifest

wds = pytest.importorskip("webdataset")

Q = {"progress": False}


def _read(out: Path, split: str) -> dict[str, dict]:
    """Every sample of a split, read with webdataset.WebDataset from the pattern index.json gives."""
    index = json.loads((out / "index.json").read_text())
    url = str(out / index["splits"][split]["pattern"])
    # webdataset 1.0.2 leaves its shard streams for the garbage collector to close
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        samples = {s["__key__"]: s for s in wds.WebDataset(url, shardshuffle=False, empty_check=False)}
        gc.collect()
    return samples


@pytest.fixture(scope="module")
def exported(curated_frames: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wds") / "shards"
    exports.export("webdataset", curated_frames, out, shard_samples=1, **Q)
    return out


def test_webdataset_reads_every_pair_back_with_its_members_per_split(
        curated_frames: Path, exported: Path, tmp_path: Path) -> None:
    recs = {exports.sample_key(p): r for p, r in load_manifest(curated_frames).items()}
    index = json.loads((exported / "index.json").read_text())
    assert index["members"] == ["clean.mp4", "corrupted.mp4", "json", "depth.npz"]
    for split in ("train", "test"):
        samples = _read(exported, split)
        want = {k for k, r in recs.items() if r["split"] == split}
        assert set(samples) == want and index["splits"][split]["samples"] == len(want)
        assert index["splits"][split]["shards"] == len(want)  # one sample per shard asked for
        for key, s in samples.items():
            rec = recs[key]
            assert set(s) >= {"clean.mp4", "corrupted.mp4", "json", "depth.npz"}
            meta = json.loads(s["json"])
            assert meta["manifest"] == rec and meta["split"] == split and meta["pair_id"] == rec["pair_id"]
            assert meta["cameras"] == json.loads((curated_frames / rec["paths"]["cameras"]).read_text())
            # members are exactly the MP4 media.encode_frames makes of the pair's frames
            for side in ("clean", "corrupted"):
                ref = media.encode_frames(curated_frames / rec["paths"][side], tmp_path / f"{key}.{side}.mp4")
                assert s[f"{side}.mp4"] == ref.read_bytes()
            depth = np.load(io.BytesIO(s["depth.npz"]))
            for side in ("clean", "corrupted"):
                assert np.array_equal(depth[side], media.read_depth(curated_frames / rec["paths"][f"{side}_depth"]))
            assert depth["clean"].dtype == np.float32 and depth["clean"].shape == (5, 48, 64)


def test_shard_index_lists_every_shard_with_its_samples(exported: Path) -> None:
    index = json.loads((exported / "index.json").read_text())
    names = sorted(p.name for p in exported.glob("*.tar"))
    assert sorted(s["name"] for s in index["shards"]) == names
    for s in index["shards"]:
        with tarfile.open(exported / s["name"]) as tar:
            keys = sorted({m.name.split(".", 1)[0] for m in tar.getmembers()})
        assert keys == sorted(s["keys"]) and len(keys) == s["samples"]
        assert s["name"].startswith(s["split"] + "-") and (exported / s["name"]).stat().st_size == s["bytes"]


def _sample_bytes(shard: Path) -> list[int]:
    """Bytes each sample of a shard takes in it (headers and padded data), in order."""
    sizes: dict[str, int] = {}
    with tarfile.open(shard) as tar:
        for m in tar.getmembers():
            key = m.name.split(".", 1)[0]
            sizes[key] = sizes.get(key, 0) + m.offset_data - m.offset + -(-m.size // 512) * 512
    return list(sizes.values())


def _tar_file_size(content: int) -> int:
    return -(-(content + 1024) // tarfile.RECORDSIZE) * tarfile.RECORDSIZE


def test_shards_respect_the_byte_limit_and_fill_greedily(
        curated_frames: Path, exported: Path, tmp_path: Path) -> None:
    one = max(_sample_bytes(exported / s["name"])[0]
              for s in json.loads((exported / "index.json").read_text())["shards"])
    limit = _tar_file_size(one) + one // 2  # every sample fits alone; two rarely do
    out = tmp_path / "w"
    assert main(["export", "webdataset", str(curated_frames), str(out), "--shard-size", f"{limit}B",
                 "--no-progress"]) == 0
    index = json.loads((out / "index.json").read_text())
    shards = index["shards"]
    assert len(shards) > 2 and all(s["bytes"] <= limit for s in shards)
    # a shard was closed only because its split's next sample would have pushed it past the limit
    for cur, nxt in zip(shards, shards[1:]):
        if cur["split"] == nxt["split"]:
            total = sum(_sample_bytes(out / cur["name"])) + _sample_bytes(out / nxt["name"])[0]
            assert _tar_file_size(total) > limit
    assert sum(s["samples"] for s in shards) == len(load_manifest(curated_frames))


def test_one_shard_per_split_under_a_large_limit_and_no_depth(curated_frames: Path, tmp_path: Path) -> None:
    big = tmp_path / "big"
    exports.export("webdataset", curated_frames, big, shard_bytes=10**9, depth=False, **Q)
    index = json.loads((big / "index.json").read_text())
    assert index["members"] == ["clean.mp4", "corrupted.mp4", "json"]
    counts = {sp: v["samples"] for sp, v in index["splits"].items()}
    assert [s["name"] for s in index["shards"]] == ["train-000000.tar", "test-000000.tar"]
    assert counts == {sp: sum(1 for r in load_manifest(curated_frames).values() if r["split"] == sp)
                      for sp in ("train", "test")}
    samples = {**_read(big, "train"), **_read(big, "test")}
    assert set(samples) == {exports.sample_key(p) for p in load_manifest(curated_frames)}
    assert all("depth.npz" not in s for s in samples.values())


def test_same_input_same_shard_bytes_whatever_the_worker_count(curated_frames: Path, tmp_path: Path) -> None:
    exports.export("webdataset", curated_frames, tmp_path / "a", shard_samples=3, workers=1, **Q)
    exports.export("webdataset", curated_frames, tmp_path / "b", shard_samples=3, workers=4, **Q)
    for p in sorted((tmp_path / "a").iterdir()):
        assert p.read_bytes() == (tmp_path / "b" / p.name).read_bytes(), p.name


def test_shard_size_parsing() -> None:
    assert exports.parse_shard_size("512MB") == (512 * 10**6, None)
    assert exports.parse_shard_size("1.5GiB") == (int(1.5 * 2**30), None)
    assert exports.parse_shard_size("100samples") == (None, 100)
    for bad in ("512", "12 parsecs", "0MB", "2.5samples", "MB"):
        with pytest.raises(ValueError, match="shard size"):
            exports.parse_shard_size(bad)


def test_float16_depth_is_smaller_within_half_precision_and_refuses_what_it_cannot_hold(
        curated_frames: Path, tmp_path: Path) -> None:
    out = tmp_path / "h"
    assert main(["export", "webdataset", str(curated_frames), str(out), "--depth-float16", "--no-progress"]) == 0
    assert json.loads((out / "index.json").read_text())["depth_dtype"] == "float16"
    recs = {exports.sample_key(p): r for p, r in load_manifest(curated_frames).items()}
    for key, s in _read(out, "train").items():
        d = np.load(io.BytesIO(s["depth.npz"]))
        exact = media.read_depth(curated_frames / recs[key]["paths"]["clean_depth"])
        assert d["clean"].dtype == np.float16
        np.testing.assert_allclose(d["clean"].astype(np.float32), exact, rtol=2.0**-11, atol=0)
    far = np.full((1, 2, 2), 7e4, np.float32)
    with pytest.raises(exports.ExportError, match="past float16's 65504"):
        exports.wds.depth_npz(far, far, dtype="float16")
    assert np.load(io.BytesIO(exports.wds.depth_npz(far, far)))["clean"][0, 0, 0] == np.float32(7e4)
