"""morphgs export on bad input: clear typed errors naming the folder, pair, file or option, and
nothing written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from PIL import Image

import morphgs
from morphgs import exports
from morphgs.cli import main

Q = {"progress": False}


@pytest.fixture()
def copy(curated_frames: Path, tmp_path: Path) -> Path:
    """A private copy of the curated folder to break."""
    d = tmp_path / "data"
    shutil.copytree(curated_frames, d)
    return d


def _rewrite_manifest(root: Path, edit) -> str:  # type: ignore[no-untyped-def]
    path = root / "manifest.jsonl"
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    edit(recs[0])
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    return str(recs[0]["pair_id"])


def test_missing_folder_is_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no-such"):
        exports.export("diffsynth", tmp_path / "no-such", tmp_path / "out", **Q)


def test_a_folder_without_a_manifest_is_not_a_curated_folder(tmp_path: Path) -> None:
    (tmp_path / "frames").mkdir()
    Image.new("RGB", (16, 16)).save(tmp_path / "frames" / "00000.png")
    with pytest.raises(exports.ExportError, match="not a curated folder"):
        exports.export("webdataset", tmp_path, tmp_path.parent / "out-x", **Q)
    assert not (tmp_path.parent / "out-x").exists()
    assert issubclass(exports.ExportError, morphgs.MorphgsError) and issubclass(exports.ExportError, ValueError)


def test_a_pair_whose_files_are_missing_is_named_and_nothing_is_written(copy: Path, tmp_path: Path) -> None:
    pid = sorted(morphgs.curation.load_manifest(copy))[-1]
    rec = morphgs.curation.load_manifest(copy)[pid]
    (copy / rec["paths"]["corrupted"] / "00003.png").unlink()
    for fmt in ("diffsynth", "webdataset", "difix"):
        with pytest.raises(exports.ExportError, match=f"pair {pid} lists .*corrupted/00003.png, which is missing"):
            exports.export(fmt, copy, tmp_path / fmt, **Q)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_a_manifest_line_missing_a_field_is_named(copy: Path, tmp_path: Path) -> None:
    pid = _rewrite_manifest(copy, lambda r: r.pop("frames"))
    with pytest.raises(exports.ExportError, match=f"pair {pid} has no 'frames' field"):
        exports.export("videox-fun", copy, tmp_path / "o", **Q)
    pid = _rewrite_manifest(copy, lambda r: r.update(frames=5, split="validation"))
    with pytest.raises(exports.ExportError, match="split 'validation' is not train or test"):
        exports.export("videox-fun", copy, tmp_path / "o", **Q)


def test_frames_of_another_size_than_the_manifest_says_are_refused(copy: Path, tmp_path: Path) -> None:
    rec = next(iter(morphgs.curation.load_manifest(copy).values()))
    Image.new("RGB", (32, 32)).save(copy / rec["paths"]["clean"] / "00000.png")
    with pytest.raises(exports.ExportError, match="00000.png: frame of 32x32, but the manifest says"):
        exports.export("thedenk", copy, tmp_path / "o", **Q)


def test_out_may_not_be_or_hold_the_curated_folder(curated_frames: Path) -> None:
    for out in (curated_frames, curated_frames.parent):
        with pytest.raises(exports.ExportError, match="would hold"):
            exports.export("diffsynth", curated_frames, out, overwrite=True, **Q)


def test_out_that_is_a_file_is_refused(curated_frames: Path, tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(exports.ExportError, match="not a folder"):
        exports.export("diffsynth", curated_frames, tmp_path / "f", overwrite=True, **Q)
    assert (tmp_path / "f").read_text() == "x"


def test_video_pairs_cannot_go_to_difix(curated_video: Path, tmp_path: Path) -> None:
    with pytest.raises(morphgs.MorphgsError, match="written as video"):
        exports.export("difix", curated_video, tmp_path / "d")
    assert list(tmp_path.iterdir()) == []


def test_depth_asked_for_but_missing(curated_video: Path, tmp_path: Path) -> None:
    with pytest.raises(exports.ExportError, match="has no depth maps"):
        exports.export("webdataset", curated_video, tmp_path / "w", depth=True, **Q)


def test_bad_options(curated_frames: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(exports.ExportError, match="unknown export format 'lance'"):
        exports.export("lance", curated_frames, tmp_path / "o")
    with pytest.raises(TypeError):
        exports.export("videox-fun", curated_frames, tmp_path / "o", shard_bytes=5)
    with pytest.raises(exports.ExportError, match="prompt is empty"):
        exports.export("diffsynth", curated_frames, tmp_path / "o", prompt=" ", **Q)
    d = str(curated_frames)
    assert main(["export", "diffsynth", d, str(tmp_path / "o"), "--shard-size", "1GB"]) == 1
    assert "--shard-size applies to webdataset, not diffsynth" in capsys.readouterr().err
    assert main(["export", "webdataset", d, str(tmp_path / "o"), "--shard-size", "1000"]) == 1
    assert "needs a unit" in capsys.readouterr().err
    caps = tmp_path / "caps.json"
    caps.write_text('["not", "an", "object"]')
    assert main(["export", "thedenk", d, str(tmp_path / "o"), "--captions", str(caps)]) == 1
    assert "captions must be one JSON object" in capsys.readouterr().err
    assert main(["export", "thedenk", d, str(tmp_path / "o"), "--captions", str(tmp_path / "none.json")]) == 1
    assert "no such captions file" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["caps.json"]
