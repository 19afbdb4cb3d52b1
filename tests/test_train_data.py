"""PairDataset over real curated folders: windows, crops, flips, cameras, references, the
manifest's split, shard merging, the loop's sampler, and every bad input named."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from morphgs import media
from morphgs.data import DatasetError, EpochSampler, PairDataset, load_records, train_loader
from train_helpers import curated


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return curated(tmp_path_factory.mktemp("pairs") / "ds", depth=True)


def _u8_to_unit(frames: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(frames.astype(np.float32) / 127.5 - 1.0).permute(3, 0, 1, 2)


def test_training_windows_are_the_frames_on_disk_at_a_seeded_offset_and_crop(data: Path) -> None:
    ds = PairDataset(data, "train", frames=4, size=(16, 24))
    a, b, c = ds[(0, 11)], ds[(0, 11)], ds[(0, 12)]
    assert torch.equal(a["corrupted"], b["corrupted"]) and a["start"] == b["start"]
    assert a["corrupted"].shape == (3, 4, 16, 24) and a["clean"].dtype == torch.float32
    rec = ds.records[0]
    for s in (a, c):
        y0, x0, t0 = s["y0"], s["x0"], s["start"]
        for side, path in (("clean", rec.clean), ("corrupted", rec.corrupted)):
            disk = media.read_clip(path)[t0:t0 + 4, y0:y0 + 16, x0:x0 + 24]
            torch.testing.assert_close(s[side], _u8_to_unit(disk), rtol=0, atol=1e-6)
    starts = {(w.start, w.y0, w.x0) for w in (ds.window(0, seed) for seed in range(20))}
    assert len(starts) > 5  # the seed moves the window
    assert a["clean"].min() >= -1 and a["clean"].max() <= 1


def test_evaluation_takes_the_centre_clip_and_crop_whatever_the_key(data: Path) -> None:
    ds = PairDataset(data, "test", frames=4, size=(16, 24))
    assert not ds.train
    s0, s1 = ds[0], ds[(0, 99)]
    assert (s0["start"], s0["y0"], s0["x0"]) == ((8 - 4) // 2, (40 - 16) // 2, (48 - 24) // 2)
    assert torch.equal(s0["clean"], s1["clean"])


def test_flips_mirror_the_crop_and_the_intrinsics(data: Path) -> None:
    ds = PairDataset(data, "train", frames=2, size=(16, 24), flip=True, cameras=True)
    plain = PairDataset(data, "train", frames=2, size=(16, 24), cameras=True)
    seed = next(s for s in range(100) if ds.window(0, s).flip)
    flipped = ds[(0, seed)]
    ref = plain[(0, seed)]  # same window draw, no flip allowed
    assert (ref["start"], ref["y0"], ref["x0"]) == (flipped["start"], flipped["y0"], flipped["x0"])
    assert torch.equal(flipped["clean"], ref["clean"].flip(-1))
    cams = json.loads(ds.records[0].cameras.read_text())  # type: ignore[union-attr]
    K = np.asarray(cams["K"][flipped["start"]])
    assert ref["K"][0, 0, 2].item() == pytest.approx(K[0, 2] - ref["x0"])
    assert ref["K"][0, 1, 2].item() == pytest.approx(K[1, 2] - ref["y0"])
    assert flipped["K"][0, 0, 0].item() == pytest.approx(-K[0, 0])
    assert flipped["K"][0, 0, 2].item() == pytest.approx(24 - (K[0, 2] - ref["x0"]))
    assert flipped["world_to_camera"].shape == (2, 4, 4)


def test_depth_and_reference_frames_come_with_the_clip(data: Path) -> None:
    ds = PairDataset(data, "train", frames=4, size=None, depth=True, reference=2)
    s = ds[(1, 5)]
    rec = ds.records[1]
    depth = media.read_depth(rec.clean_depth)[s["start"]:s["start"] + 4]  # type: ignore[arg-type]
    np.testing.assert_array_equal(s["clean_depth"][0].numpy(), depth)
    assert s["reference"].shape == (3, 2, 40, 48)
    clean = media.read_clip(rec.clean)
    window = range(s["start"], s["start"] + 4)
    # each reference frame is a clean frame from outside the window
    for r in range(2):
        matches = [i for i in range(8) if torch.equal(s["reference"][:, r], _u8_to_unit(clean[i:i + 1])[:, 0])]
        assert matches and not set(matches) & set(window)


def test_split_comes_from_the_manifest_and_shards_are_merged(data: Path, tmp_path: Path) -> None:
    train, test = PairDataset(data, "train", frames=2), PairDataset(data, "test", frames=2)
    assert {r.pair_id.split("/")[0] for r in train.records} == {"sample-1"}
    assert {r.pair_id.split("/")[0] for r in test.records} == {"sample-0"}
    # the same pairs split over two shard manifests read back as one dataset
    copy = tmp_path / "sharded"
    shutil.copytree(data, copy)
    lines = (copy / "manifest.jsonl").read_text().splitlines(keepends=True)
    (copy / "manifest.jsonl").unlink()
    (copy / "manifest-shard000-of002.jsonl").write_text("".join(lines[::2]))
    (copy / "manifest-shard001-of002.jsonl").write_text("".join(lines[1::2]))
    assert [r.pair_id for r in load_records(copy)] == [r.pair_id for r in load_records(data)]
    assert len(PairDataset(copy, "all", frames=2)) == len(lines)


def test_sampler_shards_ranks_disjointly_and_resumes_mid_epoch() -> None:
    n = 7
    r0 = EpochSampler(n, seed=3, rank=0, world_size=2)
    r1 = EpochSampler(n, seed=3, rank=1, world_size=2)
    e0 = {i for i, _ in r0.keys(0)}
    e1 = {i for i, _ in r1.keys(0)}
    assert len(e0) == len(e1) == 3 and not e0 & e1
    it = iter(r0)
    first = [next(it) for _ in range(8)]  # over two and a bit epochs
    resumed = iter(EpochSampler(n, seed=3, rank=0, world_size=2, start=5))
    assert [next(resumed) for _ in range(3)] == first[5:8]
    assert r0.keys(0) != r0.keys(1)  # each epoch its own order and seeds


def test_loader_workers_give_the_single_process_stream(data: Path) -> None:
    ds = PairDataset(data, "train", frames=2, size=(16, 16))
    one = iter(train_loader(ds, batch_size=1, num_workers=0, seed=1, rank=0, world_size=1, start_batch=1))
    two = iter(train_loader(ds, batch_size=1, num_workers=2, seed=1, rank=0, world_size=1, start_batch=1))
    for _ in range(4):
        a, b = next(one), next(two)
        assert a["pair_id"] == b["pair_id"] and torch.equal(a["corrupted"], b["corrupted"])


# ---- bad input: every error names the folder, pair or file ----


def test_empty_folder_and_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no manifest"):
        PairDataset(tmp_path, "train")
    with pytest.raises(FileNotFoundError, match="nope"):
        PairDataset(tmp_path / "nope", "train")


def test_a_manifest_line_whose_files_are_missing(data: Path, tmp_path: Path) -> None:
    copy = tmp_path / "ds"
    shutil.copytree(data, copy)
    rec = load_records(copy)[0]
    shutil.rmtree(rec.corrupted)
    with pytest.raises(DatasetError, match=f"{rec.pair_id}.*{rec.corrupted.name}.*missing"):
        PairDataset(copy, "all", frames=2)


def test_a_split_without_pairs(data: Path, tmp_path: Path) -> None:
    copy = tmp_path / "ds"
    shutil.copytree(data, copy)
    lines = [ln for ln in (copy / "manifest.jsonl").read_text().splitlines() if '"split":"train"' in ln]
    (copy / "manifest.jsonl").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="no pairs in split 'test'.*2 train and 0 test"):
        PairDataset(copy, "test")


def test_a_clip_shorter_than_f(data: Path) -> None:
    with pytest.raises(DatasetError, match=r"has 8 frames, shorter than the 9 frames"):
        PairDataset(data, "train", frames=9)
    with pytest.raises(DatasetError, match=r"6 frames \+ 3 reference frames"):
        PairDataset(data, "train", frames=6, reference=3)


def test_a_crop_larger_than_the_frames(data: Path) -> None:
    with pytest.raises(DatasetError, match="crop 64x64.*40x48"):
        PairDataset(data, "train", frames=2, size=(64, 64))


def test_frames_of_different_sizes(data: Path, tmp_path: Path) -> None:
    from PIL import Image

    copy = tmp_path / "ds"
    shutil.copytree(data, copy)
    ds = PairDataset(copy, "train", frames=8)
    bad = ds.records[0].clean / "00003.png"
    Image.new("RGB", (20, 10)).save(bad)
    with pytest.raises(media.MediaError, match="00003.png.*20x10"):
        ds[(0, 0)]


def test_an_unreadable_png_is_named_even_from_a_worker(data: Path, tmp_path: Path) -> None:
    copy = tmp_path / "ds"
    shutil.copytree(data, copy)
    ds = PairDataset(copy, "test", frames=8)
    bad = ds.records[0].corrupted / "00005.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    with pytest.raises(media.MediaError, match="00005.png: not a readable image"):
        ds[0]
    loader = torch.utils.data.DataLoader(ds, batch_size=1, num_workers=1)
    with pytest.raises(media.MediaError, match="00005.png"):
        next(iter(loader))
