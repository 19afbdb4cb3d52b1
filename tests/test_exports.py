"""morphgs export for the video trainers (DiffSynth-Studio, VideoX-Fun, TheDenk) and Difix3D, on real
curated folders made by morphgs.curate (tests/conftest.py): layouts and metadata as each trainer's
loader reads them, the split, warnings, refusing to overwrite, atomicity and determinism."""

from __future__ import annotations

import csv
import glob
import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import morphgs
from morphgs import exports, media
from morphgs.cli import main
from morphgs.curation import load_manifest

Q = {"progress": False}


def _splits(dataset: Path) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {"train": set(), "test": set()}
    for pid, rec in load_manifest(dataset).items():
        out[rec["split"]].add(exports.sample_key(pid))
    return out


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _pngs(folder: Path) -> np.ndarray:
    return media.read_clip(folder)


def _assert_video_matches_frames(mp4: Path, folder: Path) -> None:
    """The MP4 decodes to the frames it came from: same count and size, only H.264's error (on these
    tiny 64x48 renders 4:2:0 chroma costs about 5 levels on average and 1 of mean bias; the colour
    matrix itself is checked on flat colours in test_media)."""
    got, want = media.read_clip(mp4).astype(np.float64), _pngs(folder).astype(np.float64)
    assert got.shape == want.shape
    assert np.abs(got - want).mean() < 7.0
    assert np.abs((got - want).mean(axis=(0, 1, 2))).max() < 2.0


def test_diffsynth_metadata_csv_has_relative_video_and_control_columns_per_split(
        curated_frames: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    caps = {"sample-0": "a procedural room, clean render"}
    summary = exports.export("diffsynth", curated_frames, out, captions=caps, reference_frame=2, **Q)
    recs = {exports.sample_key(p): r for p, r in load_manifest(curated_frames).items()}
    splits = _splits(curated_frames)
    assert summary.counts == {s: len(k) for s, k in splits.items()}
    for split, name in (("train", "metadata.csv"), ("test", "metadata_test.csv")):
        with open(out / name, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        assert list(rows[0]) == ["video", "prompt", "control_video", "reference_image"]
        keys = {Path(r["video"]).stem for r in rows}
        assert keys == splits[split]
        for r in rows:
            rec = recs[Path(r["video"]).stem]
            for col in ("video", "control_video", "reference_image"):
                assert not os.path.isabs(r[col]) and (out / r[col]).is_file()
            assert r["prompt"] == (caps["sample-0"] if rec["scene"] == "sample-0" else "remove degradation")
            _assert_video_matches_frames(out / r["video"], curated_frames / rec["paths"]["clean"])
            _assert_video_matches_frames(out / r["control_video"], curated_frames / rec["paths"]["corrupted"])
            assert (out / r["reference_image"]).read_bytes() == \
                (curated_frames / rec["paths"]["clean"] / "00002.png").read_bytes()
    info = json.loads((out / "export.json").read_text())
    assert info["format"] == "diffsynth" and info["source"] == str(curated_frames.resolve())
    assert {p["pair_id"] for p in info["pairs"]} == set(load_manifest(curated_frames))


def test_videox_fun_metadata_json_entries_and_matching_train_control_names(
        curated_frames: Path, tmp_path: Path) -> None:
    out = tmp_path / "vxf"
    exports.export("videox-fun", curated_frames, out, prompt="fix the render", **Q)
    splits = _splits(curated_frames)
    for split, name in (("train", "metadata.json"), ("test", "metadata_test.json")):
        rows = json.loads((out / name).read_text())
        assert {Path(r["file_path"]).stem for r in rows} == splits[split]
        for r in rows:
            assert set(r) == {"file_path", "control_file_path", "text", "type", "width", "height"}
            assert r["type"] == "video" and r["text"] == "fix the render" and (r["width"], r["height"]) == (64, 48)
            assert r["file_path"].startswith("train/") and r["control_file_path"].startswith("control/")
            assert Path(r["file_path"]).name == Path(r["control_file_path"]).name
            # ImageVideoControlDataset opens os.path.join(data_root, path)
            for col in ("file_path", "control_file_path"):
                assert media.clip_info(os.path.join(out, r[col])) == (5, 48, 64)


def test_thedenk_layout_is_what_its_dataset_and_prepare_scripts_read(curated_frames: Path, tmp_path: Path) -> None:
    out = tmp_path / "denk"
    exports.export("thedenk", curated_frames, out, **Q)
    splits = _splits(curated_frames)
    for split, keys in splits.items():
        d = out / split
        # ControlnetDataset: glob the control dir, then latents/text embeddings named by the basename;
        # prepare_vae_latents.py globs videos/, prepare_text_embeddings.py reads row["video"], row["caption"]
        control = sorted(os.path.basename(p) for p in glob.glob(os.path.join(d / "controlnet_videos", "*.mp4")))
        videos = sorted(os.path.basename(p) for p in glob.glob(os.path.join(d / "videos", "*.mp4")))
        assert control == videos == sorted(f"{k}.mp4" for k in keys)
        with open(d / "captions.csv", newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        assert sorted(r["video"] for r in rows) == videos and all(r["caption"] for r in rows)
        clips = json.loads((d / "clips.json").read_text())
        for name in videos:
            info = media.clip_info(d / "videos" / name)
            assert info == media.clip_info(d / "controlnet_videos" / name) == (5, 48, 64)
            assert clips[name]["frames"] == 5 and (clips[name]["width"], clips[name]["height"]) == (64, 48)


def test_difix_format_delegates_to_export_difix_and_export_difix_still_works(
        curated_frames: Path, tmp_path: Path) -> None:
    out = tmp_path / "difix"
    assert main(["export", "difix", str(curated_frames), str(out), "--relative", "--no-progress"]) == 0
    assert main(["export-difix", str(curated_frames), str(tmp_path / "plain.json")]) == 0
    via_export = json.loads((out / "data.json").read_text())
    plain = json.loads((tmp_path / "plain.json").read_text())
    assert via_export.keys() == plain.keys() and all(via_export[s].keys() == plain[s].keys() for s in plain)
    n = sum(r["frames"] for r in load_manifest(curated_frames).values())
    assert sum(len(v) for v in via_export.values()) == n
    for split in via_export.values():
        for item in split.values():
            assert not os.path.isabs(item["image"]) and (out / item["image"]).is_file()


def test_video_curated_pairs_are_copied_byte_for_byte(curated_video: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    exports.export("diffsynth", curated_video, out, reference_frame=0, **Q)
    for pid, rec in load_manifest(curated_video).items():
        key = exports.sample_key(pid)
        assert (out / "videos" / f"{key}.mp4").read_bytes() == (curated_video / rec["paths"]["clean"]).read_bytes()
        assert (out / "control_videos" / f"{key}.mp4").read_bytes() == \
            (curated_video / rec["paths"]["corrupted"]).read_bytes()
        with Image.open(out / "reference_images" / f"{key}.png") as im:
            ref = np.asarray(im.convert("RGB"))
        assert np.array_equal(ref, media.read_clip(curated_video / rec["paths"]["clean"], count=1)[0])


def test_trainer_shape_warnings_and_odd_sizes_padded(curated_odd: Path, tmp_path: Path) -> None:
    with pytest.warns(morphgs.MorphgsWarning) as rec:
        exports.export("videox-fun", curated_odd, tmp_path / "vxf", **Q)
    msgs = [str(w.message) for w in rec]
    assert any("not 4k+1" in m and "4 frames" in m for m in msgs)
    assert any("34x26, not divisible by 16" in m for m in msgs)
    rows = json.loads((tmp_path / "vxf" / "metadata.json").read_text())
    for r in rows:
        assert (r["width"], r["height"]) == (34, 26)  # H.264 yuv420p pads odd sides
        assert media.clip_info(tmp_path / "vxf" / r["file_path"]) == (4, 26, 34)
    info = json.loads((tmp_path / "vxf" / "export.json").read_text())
    assert info["warnings"] == msgs


def test_cli_prints_warnings_and_the_summary(
        curated_odd: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", "thedenk", str(curated_odd), str(tmp_path / "d"), "--no-progress"]) == 0
    cap = capsys.readouterr()
    assert "morphgs export: warning:" in cap.err and "not 4k+1" in cap.err
    assert "morphgs export thedenk:" in cap.out


def test_existing_export_is_refused_unless_overwrite_and_kept_when_an_export_fails(
        curated_frames: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ds"
    exports.export("diffsynth", curated_frames, out, **Q)
    before = _tree(out)
    with pytest.raises(exports.ExportError, match="--overwrite"):
        exports.export("diffsynth", curated_frames, out, **Q)
    assert main(["export", "diffsynth", str(curated_frames), str(out), "--no-progress"]) == 1
    assert "exists and is not empty" in capsys.readouterr().err
    # a failing export (reference frame past the clip, found after the clips are encoded) leaves the
    # old export as it was and no temporary behind
    with pytest.raises(exports.ExportError, match="reference frame 99"):
        exports.export("diffsynth", curated_frames, out, overwrite=True, reference_frame=99, **Q)
    assert _tree(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
    # overwrite replaces it
    exports.export("diffsynth", curated_frames, out, overwrite=True, reference_frame=1, **Q)
    assert (out / "reference_images").is_dir()


def test_failed_export_leaves_nothing(curated_frames: Path, tmp_path: Path) -> None:
    with pytest.raises(exports.ExportError):
        exports.export("diffsynth", curated_frames, tmp_path / "ds", reference_frame=5, **Q)
    assert list(tmp_path.iterdir()) == []


def test_same_input_same_bytes_whatever_the_worker_count(curated_frames: Path, tmp_path: Path) -> None:
    exports.export("videox-fun", curated_frames, tmp_path / "a", workers=1, **Q)
    exports.export("videox-fun", curated_frames, tmp_path / "b", workers=3, **Q)
    assert _tree(tmp_path / "a") == _tree(tmp_path / "b")


def test_config_filter_and_captions_file(curated_frames: Path, tmp_path: Path) -> None:
    caps = tmp_path / "caps.json"
    pid = sorted(load_manifest(curated_frames))[0]
    caps.write_text(json.dumps({pid: "one pair's own caption"}))
    assert main(["export", "videox-fun", str(curated_frames), str(tmp_path / "v"), "--captions", str(caps),
                 "--config", "morphological", "--no-progress"]) == 0
    rows = json.loads((tmp_path / "v" / "metadata.json").read_text()) + \
        json.loads((tmp_path / "v" / "metadata_test.json").read_text())
    texts = {Path(r["file_path"]).stem: r["text"] for r in rows}
    assert texts.pop(exports.sample_key(pid)) == "one pair's own caption"
    assert set(texts.values()) == {"remove degradation"}
    with pytest.raises(exports.ExportError, match="no finished pairs of config blur2d"):
        exports.export("videox-fun", curated_frames, tmp_path / "w", configs=["blur2d"], **Q)


def test_keys_are_safe_names_and_stay_unique() -> None:
    from morphgs.exports.source import _unique_keys

    assert exports.sample_key("garden.v2/morphological@2.0/0003") == "garden-v2_morphological-2-0_0003"
    keys = _unique_keys(["a.b/c/0000", "a-b/c/0000", "x/c/0000"])
    assert keys["x/c/0000"] == "x_c_0000"
    assert len(set(keys.values())) == 3 and keys["a.b/c/0000"].startswith("a-b_c_0000-")
