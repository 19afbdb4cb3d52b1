"""morphgs curate end to end: synthetic and shared-fixture scenes, resume after SIGKILL, workers,
shards, a bad scene, Ray, the Difix3D export and the preview."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import morphgs
from morphgs import synthetic
from morphgs.cli import main
from morphgs.curation import load_manifest, scene_split

SMALL = ["--frames", "3", "--size", "48x32", "--no-progress"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory, fixtures_dir: Path) -> list[str]:
    """A synthetic scene file, and a folder with a shared fixture plus a COLMAP model."""
    d = tmp_path_factory.mktemp("scenes")
    morphgs.save_ply(synthetic.scene(n_gaussians=6000, seed=2), d / "room.ply")
    f = d / "fixture"
    (f / "sparse" / "0").mkdir(parents=True)
    (f / "splatapult_test.ply").write_bytes((fixtures_dir / "splatapult_test.ply").read_bytes())
    # three cameras on a line looking along +y at the fixture (ATTRIBUTION.md: splatapult test.ply)
    (f / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 96 64 80 80 48 32\n")
    lines = []
    for i, x in enumerate((-0.4, 0.0, 0.4)):
        # R maps world (x, y, z) to camera (x, -z, y): looking along +y, z up; camera at (x, -4, 0)
        # R = [[1,0,0],[0,0,-1],[0,1,0]] is +90 deg about x: q = (cos45, sin45, 0, 0); t = -R C
        lines.append(f"{i + 1} 0.7071067811865476 0.7071067811865476 0 0 {-x} 0 4 1 img{i}.png\n")
    (f / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")
    return [str(d / "room.ply"), str(f)]


def _image(path: Path | str) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / "pairs").rglob("*")) if p.is_file()}


def _records(root: Path) -> dict[str, dict]:
    out = {}
    for k, r in load_manifest(root).items():
        r = dict(r)
        r.pop("timings")
        out[k] = r
    return out


def test_curate_writes_pairs_manifest_depth_and_cameras_then_resumes(tmp_path: Path, scenes: list[str]) -> None:
    out = tmp_path / "ds"
    rc = main(["curate", *scenes, "--out", str(out), "--config", "morphological", "--config", "blur2d",
               "-k", "2", "--depth", *SMALL])
    assert rc == 0
    recs = load_manifest(out)
    assert len(recs) == 2 * 2 * 2
    r = recs["room/morphological/0001"]
    assert r["config"] == {"name": "morphological", "kind": "perturb",
                           **morphgs.PerturbConfig.preset("morphological").to_dict()}
    assert r["frames"] == 3 and r["resolution"] == [48, 32] and r["depth"] is True
    assert r["morphgs_version"] == morphgs.__version__
    assert r["split"] in ("train", "test") and set(r["timings"]) >= {"render", "total"}
    assert recs["room/blur2d/0001"]["seed"] == r["seed"] != recs["room/morphological/0000"]["seed"]
    for rec in recs.values():
        d = out / rec["paths"]["dir"]
        for side in ("clean", "corrupted"):
            pngs = sorted((d / side).glob("*.png"))
            assert [p.name for p in pngs] == ["00000.png", "00001.png", "00002.png"]
            assert _image(pngs[0]).shape == (32, 48, 3)
            assert len(list((d / side).glob("*.depth.exr"))) == 3
        cams = morphgs.Cameras.from_dict(json.loads((d / "cameras.json").read_text()))
        assert len(cams) == 3 and (cams.width, cams.height) == (48, 32)
    # the fixture folder's COLMAP cameras were used: its path starts at the first recorded camera
    fc = morphgs.Cameras.from_dict(json.loads((out / "pairs/fixture/blur2d/0000/cameras.json").read_text()))
    np.testing.assert_allclose(fc[0].center, [-0.4, -4.0, 0.0], atol=1e-9)
    # the clean side is the render of the scene from the recorded cameras
    clean = morphgs.render(morphgs.load(Path(scenes[0])), morphgs.Cameras.from_dict(
        json.loads((out / "pairs/room/morphological/0000/cameras.json").read_text())))
    png = _image(out / "pairs/room/morphological/0000/clean/00001.png")
    np.testing.assert_array_equal(png, clean.to_uint8()[1])
    # rerun: everything is skipped, nothing rewritten
    before = {p: p.stat().st_mtime_ns for p in (out / "pairs").rglob("*.png")}
    summary = morphgs.curate(scenes, out, configs=["morphological", "blur2d"], pairs_per_scene=2, frames=3,
                             resolution=(48, 32), depth=True, progress=False)
    assert (summary.done, summary.skipped, summary.ok) == (0, 8, True)
    assert before == {p: p.stat().st_mtime_ns for p in (out / "pairs").rglob("*.png")}
    # other settings into the same folder are refused
    assert main(["curate", *scenes, "--out", str(out), "--config", "blur2d", "-k", "1", "--frames", "4",
                 "--size", "48x32", "--depth", "--no-progress"]) == 2


def test_bad_scene_is_reported_and_skipped_while_others_finish(tmp_path: Path, scenes: list[str],
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\0")
    rc = main(["curate", str(bad), scenes[0], str(tmp_path / "nope"), "--out", str(tmp_path / "ds"),
               "--config", "blur2d", "-k", "2", *SMALL])
    assert rc == 1
    err = capsys.readouterr().err
    assert "FAILED broken" in err and "nope" in err and "2 pairs made" in err
    assert set(load_manifest(tmp_path / "ds")) == {"room/blur2d/0000", "room/blur2d/0001"}


def _curate_cmd(scene: str, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "morphgs.cli", "curate", scene, "--out", str(out), "--config", "morphological",
            "-k", "6", "--frames", "8", "--size", "96x64", "--depth", "--no-progress", *extra]


def test_killed_run_resumes_to_the_same_bytes_as_an_uninterrupted_run(tmp_path: Path, scenes: list[str]) -> None:
    env = dict(os.environ, MORPHGS_NUM_THREADS="2")
    ref, killed = tmp_path / "ref", tmp_path / "killed"
    subprocess.run(_curate_cmd(scenes[0], ref), env=env, check=True, capture_output=True)
    proc = subprocess.Popen(_curate_cmd(scenes[0], killed), env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    man = killed / "manifest.jsonl"
    while time.monotonic() < deadline and proc.poll() is None:
        if man.is_file() and man.read_text().count("\n") >= 1:
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done_at_kill = man.read_text().count("\n") if man.is_file() else 0
    assert done_at_kill < 6, "the run finished before it could be killed"
    # what the killed run left is never mistaken for finished pairs
    assert len(load_manifest(killed)) == done_at_kill
    rc = subprocess.run(_curate_cmd(scenes[0], killed), env=env, capture_output=True).returncode
    assert rc == 0
    assert _files(killed) == _files(ref)
    assert _records(killed) == _records(ref)
    assert not any((killed / ".tmp").iterdir()) if (killed / ".tmp").exists() else True


def test_workers_and_shards_give_the_same_pairs_as_one_process(tmp_path: Path, scenes: list[str]) -> None:
    args = dict(configs=["blur2d", "spatial"], pairs_per_scene=2, frames=2, resolution=(48, 32), progress=False)
    one = morphgs.curate(scenes, tmp_path / "one", **args)
    two = morphgs.curate(scenes, tmp_path / "two", workers=2, **args)
    assert one.ok and two.ok and two.done == 8
    assert _files(tmp_path / "one") == _files(tmp_path / "two")
    for i in range(3):
        s = morphgs.curate(scenes, tmp_path / "sharded", shard_index=i, num_shards=3, **args)
        assert s.ok
    assert sorted(p.name for p in (tmp_path / "sharded").glob("manifest*.jsonl")) == [
        f"manifest-shard{i:03d}-of003.jsonl" for i in range(3)]
    assert _files(tmp_path / "sharded") == _files(tmp_path / "one")
    assert _records(tmp_path / "sharded") == _records(tmp_path / "one")


def test_ray_backend_on_a_local_ray_instance(tmp_path: Path, scenes: list[str]) -> None:
    # CI installs the ray extra, so there a missing Ray is a failure, not a skip
    ray = __import__("ray") if os.environ.get("CI") else pytest.importorskip("ray")
    args = dict(configs=["blur2d"], pairs_per_scene=2, frames=2, resolution=(48, 32), progress=False)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        s = morphgs.curate(scenes, tmp_path / "ray", backend="ray", workers=2, **args)
    finally:
        ray.shutdown()
    assert s.ok and s.done == 4
    local = morphgs.curate(scenes, tmp_path / "local", **args)
    assert _files(tmp_path / "ray") == _files(tmp_path / "local")


def test_builtin_sample_scenes_when_no_scene_is_given(tmp_path: Path) -> None:
    rc = main(["curate", "--out", str(tmp_path / "demo"), "--sample-gaussians", "3000", "-k", "1",
               "--config", "morphological", *SMALL])
    assert rc == 0
    assert set(load_manifest(tmp_path / "demo")) == {"sample-0/morphological/0000", "sample-1/morphological/0000"}
    png = _image(tmp_path / "demo/pairs/sample-0/morphological/0000/clean/00000.png")
    assert png.mean() > 10  # the orbit sees the room


def test_difix_export_has_what_difix3d_paired_dataset_reads(tmp_path: Path, scenes: list[str]) -> None:
    split_seed = next(s for s in range(100)
                      if {scene_split("room", test_fraction=0.5, split_seed=s),
                          scene_split("fixture", test_fraction=0.5, split_seed=s)} == {"train", "test"})
    out = tmp_path / "ds"
    assert main(["curate", *scenes, "--out", str(out), "--config", "blur2d", "-k", "1", "--test-fraction", "0.5",
                 "--split-seed", str(split_seed), *SMALL]) == 0
    data_json = tmp_path / "difix" / "data.json"
    assert main(["export-difix", str(out), str(data_json)]) == 0
    # what Difix3D's src/dataset.py PairedDataset does: json.load(f)[split], then per id
    # image / target_image / ref_image / prompt, opening the paths as given
    for split in ("train", "test"):
        with open(data_json) as f:
            data = json.load(f)[split]
        assert len(data) == 3
        for img_id in list(data.keys()):
            sample = data[img_id]
            assert sample["prompt"] == "remove degradation"
            imgs = [_image(sample[k]) for k in ("image", "target_image", "ref_image")]
            assert all(im.shape == (32, 48, 3) for im in imgs)
            assert "/corrupted/" in sample["image"] and "/clean/" in sample["target_image"]
            assert sample["ref_image"] != sample["target_image"]
    rel = tmp_path / "rel.json"
    from morphgs.curation import export_difix
    export_difix(out, rel, relative=True)
    entry = next(iter(json.loads(rel.read_text())["train"].values()))
    assert not Path(entry["image"]).is_absolute() and (tmp_path / entry["image"]).is_file()


def test_preview_writes_a_contact_sheet_and_animation(tmp_path: Path, scenes: list[str]) -> None:
    out = tmp_path / "ds"
    morphgs.curate(scenes[:1], out, configs=["blur2d", "morphological"], pairs_per_scene=1, frames=3,
                   resolution=(48, 32), progress=False)
    assert main(["preview", str(out), "--pairs", "2", "--columns", "3", "--width", "48"]) == 0
    assert _image(out / "preview" / "contact_sheet.png").shape == (2 * (2 * 34 + 14) + 2, 3 * 50 + 2, 3)
    with Image.open(out / "preview" / "preview.gif") as gif:
        assert gif.n_frames == 3 and gif.size == (2 * 48 + 6, 2 * 34 + 2)
    # MP4 animation: decode it with ffmpeg
    import subprocess

    import imageio_ffmpeg

    from morphgs.curation import preview

    _, mp4 = preview(out, out=tmp_path / "p", pairs=2, thumb_width=48, animation="mp4")
    raw = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(mp4), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
    assert len(raw) == 3 * (2 * 34 + 2) * (2 * 48 + 6) * 3


def test_video_output_writes_playable_mp4s(tmp_path: Path, scenes: list[str]) -> None:
    from morphgs.curation.preview import _frames

    out = tmp_path / "ds"
    s = morphgs.curate(scenes[:1], out, configs=["blur2d"], pairs_per_scene=1, frames=4, resolution=(48, 32),
                       video=True, progress=False)
    assert s.ok
    rec = load_manifest(out)["room/blur2d/0000"]
    assert rec["paths"]["clean"].endswith("clean.mp4")
    frames = _frames(out, rec, "clean")
    assert len(frames) == 4 and frames[0].shape == (32, 48, 3)
    png = morphgs.render(morphgs.load(scenes[0]), morphgs.Cameras.from_dict(
        json.loads((out / rec["paths"]["cameras"]).read_text()))).to_uint8()
    assert np.abs(frames[2].astype(int) - png[2]).mean() < 8  # lossy, but the same pictures


def test_curate_over_the_shared_fixture_files(tmp_path: Path, fixtures_dir: Path) -> None:
    # Real files written by other tools (see fixtures ATTRIBUTION.md), framed by for_scene orbits.
    names = ["metalsplatter_train3.ply", "splatapult_test.ply", "marcelpadilla_spot_10k.splat",
             "playcanvas_engine_test.compressed.ply"]
    s = morphgs.curate([fixtures_dir / n for n in names], tmp_path / "ds", configs=["morphological", "blur2d"],
                       pairs_per_scene=1, frames=2, resolution=(48, 32), progress=False)
    assert s.ok, s.text()
    recs = load_manifest(tmp_path / "ds")
    assert {r["scene"] for r in recs.values()} == {
        "metalsplatter_train3", "splatapult_test", "marcelpadilla_spot_10k", "playcanvas_engine_test.compressed"}
    spot = _image(tmp_path / "ds" / recs["marcelpadilla_spot_10k/morphological/0000"]["paths"]["clean"] / "00000.png")
    assert (spot.sum(axis=2) > 0).mean() > 0.05  # the orbit frames the object
