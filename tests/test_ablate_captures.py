"""`morphgs ablate` on captures given as photos (issue 35 §1): a folder `morphgs fit` reads is a
scene input; a cached, resumable clean-fit stage fits its clean scene from all its photos but the
held-out ones, the report gives each clean fit's held-out quality and names a poor one, and a
capture that cannot serve says so in one line before any long work."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from fit_helpers import make_dataset

SMALL = (48, 48)


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONWARNINGS": "ignore::DeprecationWarning"}
    return subprocess.run([sys.executable, "-m", "morphgs", *args], cwd=cwd, capture_output=True, text=True,
                          env=env, timeout=900)


def _captures(root: Path, n: int = 3, views: int = 18) -> list[str]:
    names = []
    for i in range(n):
        make_dataset(root / f"cap{i}", views=views, size=SMALL, gaussians=1500, seed=i)
        names.append(f"cap{i}")
    return names


def _study(root: Path, inputs: list[str], extra: str = "") -> Path:
    f = root / "study.toml"
    f.write_text('preset = "smoke"\n[scenes]\ninputs = ' + json.dumps(inputs) + "\n"
                 '[conditions]\ntrain = ["morphological"]\n[study]\nseeds = [0]\n'
                 '[clean]\nsteps = 120\nmin_psnr = 99.0\n' + extra, encoding="utf-8")
    return f


@pytest.fixture(scope="module")
def captured(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with three captures of photos, study.toml, and the uninterrupted study in out/ (one
    worker: the chaos and Ray runs, two workers each, must give its bytes)."""
    root = tmp_path_factory.mktemp("captures")
    _study(root, _captures(root))
    r = _cli("ablate", "--study", "study.toml", "--out", "out", "-j", "1", cwd=root)
    assert r.returncode == 0, r.stderr
    return root


def _same_results(a: Path, b: Path) -> None:
    for f in ("results.json", "results.csv", "table.md"):
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_a_capture_of_photos_is_fitted_then_studied_and_a_rerun_computes_nothing(captured: Path) -> None:
    out = captured / "out"
    runs = [json.loads(x) for x in (out / "runs.jsonl").read_text().splitlines()]
    assert runs[-1]["counts"]["cleanfits"] == {"computed": 3, "reused": 0}
    # each clean fit held out every 8th photo and says how well it renders them
    (d,) = (out / "cleanfits").glob("cap0-*")
    info = json.loads((d / "cleanfit.json").read_text())
    assert info["photos"] == 18 and info["heldout_views"] == 3 and info["steps"] == 120
    assert 5.0 < info["heldout_psnr"] < 60.0
    # the capture folder the later stages read holds the photos and the fitted scene
    (c,) = (out / "captures").glob("cap0-*")
    cap = json.loads((c / "capture.json").read_text())
    assert cap["images"] == "images" and cap["clean_fit"]["heldout_psnr"] == info["heldout_psnr"]
    assert (c / "cap0" / "scene.ply").resolve() == (d / info["ply"]).resolve()
    table = (out / "table.md").read_text()
    assert f"cap0 {info['heldout_psnr']:.2f} dB" in table
    assert "POOR clean fit (held-out PSNR below clean.min_psnr = 99 dB): cap0, cap1, cap2" in table
    # the test clips run along the capture and their clean frames are its photos, byte for byte
    (t,) = (out / "testsets").glob("*")
    ts = json.loads((t / "testset.json").read_text())
    assert ts["clean"] == "photos" and ts["clip_views"] == [list(range(8))]
    # the sparse fit's convergence: held-out capture views scored 8 times along it, in the notes
    conv = ts["convergence"]
    assert conv["steps"] == 150 and len(conv["psnr_by_step"]) >= 8 and conv["psnr_by_step"][-1][0] == 150
    assert conv["heldout_views"] and not set(conv["heldout_views"]) & set(ts["train_views"])
    assert "S8 sparse fits: 150 steps; held-out capture views at" in table
    from morphgs import media

    clean = media.read_clip(t / "clips" / "00" / "clean")
    photos = [media.read_image(captured / ts["scene"] / "images" / f"frame_{i:05d}.png") for i in range(8)]
    assert np.array_equal(clean, np.stack(photos))
    res = json.loads((out / "results.json").read_text())
    assert sorted(res["clean_fits"]) == ["cap0", "cap1", "cap2"]

    again = captured / "again"
    shutil.copytree(out, again, symlinks=True)  # a moved study folder still reads its clean fits
    r = _cli("ablate", "--study", "study.toml", "--out", "again", cwd=captured)
    assert r.returncode == 0, r.stderr
    assert "0 stage output(s) computed" in r.stderr
    _same_results(out, again)

    # the threshold is the report's alone: changing it remakes the report, no fit
    f = captured / "study.toml"
    f.write_text(f.read_text().replace("min_psnr = 99.0", "min_psnr = 1.0"))
    try:
        r = _cli("ablate", "--study", "study.toml", "--out", "again", "--recompute", cwd=captured)
    finally:
        f.write_text(f.read_text().replace("min_psnr = 1.0", "min_psnr = 99.0"))
    assert r.returncode == 0, r.stderr
    assert "1 stage output(s) computed" in r.stderr
    assert "POOR" not in (again / "table.md").read_text()


def test_sigkill_at_ten_random_moments_then_reruns_give_the_uninterrupted_bytes(captured: Path) -> None:
    """The chaos test: the study and its workers killed (SIGKILL to the process group) at 10
    seeded random moments, rerun after each; then run to the end: the results equal the
    uninterrupted run's, byte for byte.

    A moment is a point of the study's progress and a delay: kill round j once the study has
    finished e_j of its jobs in all (e_j: 10 distinct draws, sorted, spread over the study), a
    random fraction of a second later, so kills land inside jobs and between them. Tied to the
    run's own progress, not to the wall time of the uninterrupted run, so a busier or quieter
    machine still gets its kills mid-study."""
    runs = [json.loads(x) for x in (captured / "out" / "runs.jsonl").read_text().splitlines()]
    total = sum(c["computed"] for c in runs[0]["counts"].values())
    rng = np.random.default_rng(35)
    events = np.sort(rng.choice(total - 1, 10, replace=False))
    killed = 0
    for event, delay in zip(events, rng.uniform(0.0, 0.5, 10)):
        proc = subprocess.Popen([sys.executable, "-m", "morphgs", "ablate", "--study", "study.toml", "--out", "chaos",
                                 "-j", "2"], cwd=captured, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
        assert proc.stderr is not None
        before, done = total, -1
        for line in proc.stderr:  # "ablate: n job(s) to make", "  [i/n] stage/job: computed in s" per job
            if m := re.match(r"ablate: (\d+) job\(s\) to make", line):
                before = total - int(m[1])
                done = before
            elif m := re.match(r"\s*\[(\d+)/\d+\] ", line):
                done = before + int(m[1])
            if done >= event:
                break
        time.sleep(float(delay))
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            killed += 1
        proc.stderr.close()
        proc.wait(timeout=60)
    assert killed >= 8  # every moment is before the last job: all but a run outpacing its delay are killed
    r = _cli("ablate", "--study", "study.toml", "--out", "chaos", cwd=captured)
    assert r.returncode == 0, r.stderr
    _same_results(captured / "out", captured / "chaos")


def test_the_capture_study_on_a_local_ray_cluster_gives_the_same_bytes(captured: Path) -> None:
    __import__("ray") if os.environ.get("CI") else pytest.importorskip("ray")
    r = _cli("ablate", "--study", "study.toml", "--out", "ray", "--backend", "ray", "-j", "2", cwd=captured)
    assert r.returncode == 0, r.stderr
    _same_results(captured / "out", captured / "ray")


def test_a_capture_of_another_aspect_than_the_study_is_named_once(tmp_path: Path) -> None:
    """A 4:3 capture in a square study: its frames are centre-cropped, and the user reads that once,
    from the check of the inputs, not again from each worker job that reads it or the study's copy."""
    make_dataset(tmp_path / "wide", views=18, size=(64, 48), gaussians=1500, seed=3)
    make_dataset(tmp_path / "square", views=18, size=SMALL, gaussians=1500, seed=4)
    _study(tmp_path, ["wide", "square"])
    r = _cli("ablate", "--study", "study.toml", "--out", "out", "-j", "2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    crops = [ln for ln in r.stderr.splitlines() if "centre-cropped" in ln]
    assert len(crops) == 1, r.stderr
    assert crops[0].startswith("morphgs ablate: warning: ") and "wide" in crops[0] and "keeping 75 %" in crops[0]


def test_a_capture_that_cannot_serve_is_one_line_before_any_work(tmp_path: Path) -> None:
    names = _captures(tmp_path, views=18)
    # a camera whose photo is missing
    os.remove(tmp_path / "cap1" / "images" / "frame_00004.png")
    _study(tmp_path, names)
    r = _cli("ablate", "--study", "study.toml", "--out", "out", cwd=tmp_path)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "cap1" in lines[0] and "camera 4" in lines[0] and "frame_00004.png" in lines[0]
    assert not (tmp_path / "out" / "cleanfits").exists()
    # a photo that is not an image, and one of another aspect than its camera
    (tmp_path / "cap1" / "images" / "frame_00004.png").write_bytes(b"not a png")
    r = _cli("ablate", "--study", "study.toml", "--out", "out", "--dry-run", cwd=tmp_path)
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "cap1" in r.stderr and "frame_00004.png: not a readable image" in r.stderr
    from PIL import Image

    Image.new("RGB", (40, 48)).save(tmp_path / "cap1" / "images" / "frame_00004.png")
    r = _cli("ablate", "--study", "study.toml", "--out", "out", "--dry-run", cwd=tmp_path)
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "cap1: camera 4:" in r.stderr and "image is 40x48, but its camera is 48x48" in r.stderr
    # too few photos for a regime
    shutil.rmtree(tmp_path / "cap1")
    make_dataset(tmp_path / "cap1", views=6, size=SMALL, gaussians=500, seed=1)
    r = _cli("ablate", "--study", "study.toml", "--out", "out", cwd=tmp_path)
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "scene cap1 has 6 capture views, too few for regime S8" in r.stderr


def test_curate_says_to_fit_a_capture_of_photos_first(tmp_path: Path) -> None:
    make_dataset(tmp_path / "cap", views=6, size=SMALL, gaussians=300)
    r = _cli("curate", "cap", "--out", "data", "--frames", "4", cwd=tmp_path)
    assert r.returncode != 0, r.stderr
    assert "holds photos and cameras: fit it first" in r.stderr and "Traceback" not in r.stderr


def test_the_dl3dv_layout_reads_the_downscaled_photos(tmp_path: Path) -> None:
    """DL3DV's transforms.json names images/frame_XXXXX.png, the folder holds images_4/ (or
    images_8/) only: the photos are read from there, their cameras scaled to them."""
    from morphgs.fit import load_posed_images
    from PIL import Image

    root, _, cams = make_dataset(tmp_path / "dl3dv", views=6, size=(64, 48), gaussians=300)
    (root / "images_4").mkdir()
    for p in sorted((root / "images").iterdir()):
        Image.open(p).resize((16, 12), Image.Resampling.BOX).save(root / "images_4" / p.name)
    shutil.rmtree(root / "images")
    posed = load_posed_images(root)
    assert [p.parent.name for p in posed.paths] == ["images_4"] * 6
    imgs, pcams = posed.load([0, 5])
    assert imgs[0].shape == (12, 16, 3) and pcams[0].width == 16
    assert pcams[1].fx == pytest.approx(cams[5].fx / 4)
    # a photo missing from every folder stays the named file
    os.remove(root / "images_4" / "frame_00003.png")
    assert load_posed_images(root).paths[3] == root / "images" / "frame_00003.png"


def test_test_clips_follow_the_video_order_or_a_nearest_neighbour_path_through_shuffled_photos() -> None:
    from morphgs.trajectory import camera_sequence

    t = np.linspace(0, np.pi, 20)
    path = np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=1)  # a walk around half a circle
    assert camera_sequence(path) == list(range(20))  # video order kept
    perm = np.random.default_rng(0).permutation(20)
    order = camera_sequence(path[perm])  # photos with no order: walked from one end to the other
    walked = perm[order].tolist()
    assert walked in (list(range(20)), list(range(19, -1, -1)))


def test_a_colmap_capture_is_keyed_by_its_model_and_photos(tmp_path: Path) -> None:
    """A COLMAP capture (sparse/0 and images/) plans a clean fit; its key follows the model's files
    and the photos: one changed photo changes the clean fit's key and what reads it."""
    from capture_helpers import Shot, orbit_poses, pinhole, room, write_capture

    from morphgs.ablation import build_plan, load_study

    for i in range(3):
        shots = [Shot(f"p{k:03d}.png", pinhole(w2c, 48, 48)) for k, w2c in enumerate(orbit_poses(18))]
        write_capture(tmp_path / f"col{i}", room(800, seed=i), shots, points=200)
    f = _study(tmp_path, ["col0", "col1", "col2"])

    def keys() -> dict[str, str]:
        return {f"{j.ref.stage}/{j.ref.name}": j.ref.key for j in build_plan(load_study(f), tmp_path / "s")
                if j.ref.stage in ("cleanfits", "captures")}

    before = keys()
    assert sorted(k for k in before if k.startswith("cleanfits/")) == ["cleanfits/col0", "cleanfits/col1",
                                                                        "cleanfits/col2"]
    from PIL import Image

    p = tmp_path / "col1" / "images" / "p004.png"
    Image.fromarray(255 - np.asarray(Image.open(p))).save(p)
    after = keys()
    assert {k for k in before if before[k] != after[k]} == {"cleanfits/col1", "captures/col1"}


def test_a_blender_layout_transforms_json_takes_the_photo_size_from_the_photos(tmp_path: Path) -> None:
    """instant-ngp / Blender transforms.json gives camera_angle_x and no w/h: the size is the
    photo's, as instant-ngp reads it."""
    from morphgs.fit import load_posed_images

    root, _, cams = make_dataset(tmp_path / "ngp", views=6, size=(64, 48), gaussians=300)
    meta = json.loads((root / "transforms.json").read_text())
    fov = 2 * np.arctan(0.5 * 64 / meta["fl_x"])
    for k in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        meta.pop(k)
    meta["camera_angle_x"] = float(fov)
    (root / "transforms.json").write_text(json.dumps(meta))
    posed = load_posed_images(root)
    assert (posed.cameras[0].width, posed.cameras[0].height) == (64, 48)
    assert posed.cameras[2].fx == pytest.approx(cams[2].fx)
    os.remove(root / "images" / "frame_00000.png")  # no photo to read it from: the one-line error says so
    from morphgs.trajectory import CaptureError

    with pytest.raises(CaptureError, match=r"frames\[0\].*no image size .* or the frame's photo"):
        load_posed_images(root)


FIXTURE = Path(__file__).parent / "fixtures" / "captures" / "skull"


def test_the_real_smoke_preset_on_a_committed_real_capture(tmp_path: Path) -> None:
    """`--preset real-smoke` through the CLI with a real capture as the test scene (24 DSLR photos
    of a skull, COLMAP SIMPLE_RADIAL, CC BY 4.0: tests/fixtures/captures/skull/ATTRIBUTION.md):
    its clean fit comes from its photos, its sparse fits train on them and its test clip's clean
    frames are those photos (undistorted, at the study's size). The two training captures are
    renders of built-in rooms (one real capture fits in the repository)."""
    shutil.copytree(FIXTURE, tmp_path / "skull")
    for i in range(2):
        make_dataset(tmp_path / f"room{i}", views=18, size=(72, 48), gaussians=1500, seed=i)
    (tmp_path / "study.toml").write_text(
        'preset = "real-smoke"\n[scenes]\ninputs = ["skull", "room0", "room1"]\n'
        '[split]\ntrain_ids = ["room0", "room1"]\ntest_ids = ["skull"]\n'
        '[conditions]\ntrain = ["morphological"]\n[study]\nseeds = [0]\n', encoding="utf-8")
    r = _cli("ablate", "--study", "study.toml", "--out", "out", "-j", "2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out"
    (d,) = (out / "cleanfits").glob("skull-*")
    info = json.loads((d / "cleanfit.json").read_text())
    assert info["photos"] == 24 and info["heldout_views"] == 3 and info["heldout_psnr"] > 15.0
    (t,) = (out / "testsets").glob("skull-S4-*")
    ts = json.loads((t / "testset.json").read_text())
    assert ts["clean"] == "photos" and ts["train_views"] == list(range(0, 24, 4))
    from morphgs import media
    from morphgs.fit import load_posed_images

    (c,) = (out / "captures").glob("skull-*")
    posed = load_posed_images(c / "skull")  # the photos at the study's size, undistorted
    (views,) = ts["clip_views"]
    photos, _ = posed.load(views)
    assert np.array_equal(media.read_clip(t / "clips" / "00" / "clean"), np.stack(photos))
    assert photos[0].shape == (48, 72, 3)
    assert f"skull {info['heldout_psnr']:.2f} dB" in (out / "table.md").read_text()


def test_the_real_presets_need_captures(tmp_path: Path) -> None:
    r = _cli("ablate", "--preset", "real", "--out", "out", "--dry-run", cwd=tmp_path)
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "scenes.inputs: the real preset runs on real captures" in r.stderr


def _scene_folder(root: Path, views: int = 18, size: tuple[int, int] = SMALL, seed: int = 0) -> Path:
    """A posed-photo capture that also holds its scene (as a curate scene folder does)."""
    import morphgs

    folder, scene, _ = make_dataset(root, views=views, size=size, gaussians=1500, seed=seed)
    morphgs.save(scene, folder / "scene.ply")
    return folder


def test_curate_pairs_at_the_photos_have_the_photos_as_their_clean_side(tmp_path: Path) -> None:
    """`curate --trajectory photos`: pair k is run k of consecutive photos along the capture, at the
    photos' cameras; its clean frames are the photos, its corrupted frames the corrupted scene
    rendered there; a rerun makes nothing, and the same folder with render pairs is refused."""
    from morphgs import media
    from morphgs.camera import Cameras

    _scene_folder(tmp_path / "cap")
    r = _cli("curate", "cap", "--out", "data", "--frames", "8", "--size", "48x48", "--trajectory", "photos",
             "--config", "morphological", "--pairs-per-scene", "2", "--test-fraction", "0", "--no-progress",
             cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    recs = sorted((json.loads(x) for x in (tmp_path / "data" / "manifest.jsonl").read_text().splitlines()),
                  key=lambda x: x["pair_index"])
    assert [x["clean_source"] for x in recs] == ["photos", "photos"]
    for k, rec in enumerate(recs):
        d = tmp_path / "data"
        clean = media.read_clip(d / rec["paths"]["clean"])
        photos = np.stack([media.read_image(tmp_path / "cap" / "images" / f"frame_{i:05d}.png")
                           for i in range(8 * k, 8 * k + 8)])
        assert np.array_equal(clean, photos)
        assert not np.array_equal(media.read_clip(d / rec["paths"]["corrupted"]), clean)
        cams = Cameras.from_dict(json.loads((d / rec["paths"]["cameras"]).read_text()))
        assert (cams[0].width, cams[0].height) == SMALL
    r = _cli("curate", "cap", "--out", "data", "--frames", "8", "--size", "48x48", "--trajectory", "photos",
             "--config", "morphological", "--pairs-per-scene", "2", "--test-fraction", "0", "--no-progress",
             cwd=tmp_path)
    assert r.returncode == 0 and "0 pairs made, 2 already done" in r.stderr, r.stderr
    r = _cli("curate", "cap", "--out", "data", "--frames", "8", "--size", "48x48", "--trajectory", "cameras",
             "--config", "morphological", "--pairs-per-scene", "2", "--test-fraction", "0", "--no-progress",
             cwd=tmp_path)
    assert r.returncode != 0 and "made with other settings" in r.stderr, r.stderr


def test_photos_of_another_aspect_are_covered_and_cropped_with_their_cameras(tmp_path: Path) -> None:
    """A pair size of another aspect than the photos (48x48 photos in 64x48 pairs, as 4:3 or
    portrait photos in a 16:9 study): each photo is scaled to cover the pair and centre-cropped,
    pixels square, and its camera moves with it: the clean scene rendered at the pair's cameras is
    the cropped photo (a camera without the crop's shift is not)."""
    import morphgs
    from morphgs import media
    from morphgs.camera import Camera, Cameras
    from PIL import Image

    _scene_folder(tmp_path / "cap")
    r = _cli("curate", "cap", "--out", "data2", "--frames", "8", "--size", "64x48", "--trajectory", "photos",
             "--config", "morphological", "--test-fraction", "0", "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rec = json.loads((tmp_path / "data2" / "manifest.jsonl").read_text().splitlines()[0])
    d = tmp_path / "data2"
    clean = media.read_clip(d / rec["paths"]["clean"])
    assert clean.shape == (8, 48, 64, 3)
    first = media.read_image(tmp_path / "cap" / "images" / "frame_00000.png")
    covered = np.asarray(Image.fromarray(first).resize((64, 64), Image.Resampling.LANCZOS))
    assert np.array_equal(clean[0], covered[8:56])  # 48x48 -> 64x64, the middle 48 rows
    cams = Cameras.from_dict(json.loads((d / rec["paths"]["cameras"]).read_text()))
    scene = morphgs.load(tmp_path / "cap" / "scene.ply")

    def psnr(cs: list[Camera]) -> float:
        img = morphgs.render(scene, Cameras.from_list(cs)).to_uint8().astype(np.float64)
        return float(10 * np.log10(255.0**2 / np.mean((img - clean.astype(np.float64)) ** 2)))

    good = psnr(list(cams))
    unshifted = psnr([Camera(c.fx, c.fy, c.cx, c.cy + 8, c.width, c.height, c.world_to_camera, c.near, c.far)
                      for c in cams])
    assert good > 28.0 and good > unshifted + 6.0, (good, unshifted)


def test_ablate_with_photos_as_the_training_pairs_clean_side(tmp_path: Path) -> None:
    """`conditions.clean = "photo"`: every training pair of every condition sits at a run of
    photos, with the photos as its clean side; a study whose training scenes are not captures of
    photos is refused in one line."""
    names = _captures(tmp_path)
    f = _study(tmp_path, names)
    f.write_text(f.read_text().replace("[conditions]\n", '[conditions]\nclean = "photo"\n'))
    r = _cli("ablate", "--study", "study.toml", "--out", "out", "-j", "2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    from morphgs import media

    for ts in (tmp_path / "out" / "trainsets").glob("*"):
        recs = [json.loads(x) for x in (ts / "data" / "manifest.jsonl").read_text().splitlines()]
        assert recs and all(x["clean_source"] == "photos" for x in recs), ts.name
    rec = recs[0]
    clean = media.read_clip(ts / "data" / rec["paths"]["clean"])
    cap = next((tmp_path / "out" / "captures").glob(f"{rec['scene']}-*")) / rec["scene"]
    assert any(np.array_equal(clean[0], media.read_image(p)) for p in sorted((cap / "images").iterdir()))
    g = tmp_path / "builtin.toml"
    g.write_text('preset = "smoke"\n[conditions]\nclean = "photo"\n')
    r = _cli("ablate", "--study", "builtin.toml", "--out", "o2", "--dry-run", cwd=tmp_path)
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "conditions.clean = 'photo': training scene(s)" in r.stderr


def test_the_clean_fit_shrinks_photos_to_the_study_size_whatever_their_orientation() -> None:
    from morphgs.ablation.stages.cleanfits import downscale_for

    assert downscale_for((1280, 720), (128, 72)) == 10
    assert downscale_for((720, 1280), (128, 72)) == 10  # a portrait capture in a landscape study
    assert downscale_for((1920, 1440), (128, 96)) == 15 and downscale_for((100, 60), (128, 96)) == 1


def test_the_cka_probe_of_a_capture_of_portrait_and_landscape_photos_is_one_size(tmp_path: Path) -> None:
    # a phone capture mixes orientations (each photo keeps its own in the study's capture): the
    # probe is the first run of consecutive views of the most common size, read before training
    from morphgs._core import _write_png
    from morphgs.ablation.stages.training import _probe_clip

    rng = np.random.default_rng(0)
    (tmp_path / "images").mkdir()
    sizes = [(96, 72)] * 2 + [(72, 96)] * 3 + [(96, 72)] * 9  # (W, H): landscape, portrait, landscape
    views = []
    for i, (w, h) in enumerate(sizes):
        views.append(rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        _write_png(tmp_path / "images" / f"view_{i:05d}.png", views[-1])
    probe = _probe_clip(tmp_path, 8, (64, 64))
    assert probe.shape == (8, 64, 64, 3)
    np.testing.assert_array_equal(probe[0], views[5][4:68, 16:80])  # views 5..12: the first 8 in a row
    # a crop larger than the views: the whole view; too few in a row: the first of that size
    assert _probe_clip(tmp_path, 10, (128, 128)).shape == (10, 72, 96, 3)
