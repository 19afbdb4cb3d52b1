"""Real-capture layouts through `morphgs fit` and the trajectory readers: COLMAP's undistorted
layout (every image its own size), mixed portrait / landscape cameras, distorted cameras
(COLMAP SIMPLE_RADIAL / RADIAL / OPENCV / FULL_OPENCV, transforms.json k1 k2 p1 p2) undistorted
with OpenCV into the run folder, fisheye refused; each bad layout through the CLI (one line)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from capture_helpers import Shot, orbit_poses, pinhole, room, write_capture, write_colmap, write_transforms
from fit_helpers import small_config
import morphgs
from morphgs import trajectory
from morphgs.camera import Camera
from morphgs.fit import FitDataError, fit, load_posed_images
from morphgs.fit.undistort import colmap_distortion, undistort
from morphgs.trajectory import CaptureError

cv2 = pytest.importorskip("cv2")


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "morphgs.cli", *args], capture_output=True, text=True)


def _one_line_error(r: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert r.returncode != 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("morphgs fit: error: "), r.stderr
    assert "Traceback" not in r.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def _pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.5 + 0.4 * np.sin(9 * x + 2) * np.cos(7 * y - 1)


@pytest.mark.parametrize("model,params", [
    ("SIMPLE_RADIAL", (120.0, 81.3, 58.7, -0.22)),
    ("RADIAL", (120.0, 81.3, 58.7, -0.25, 0.07)),
    ("OPENCV", (120.0, 118.0, 81.3, 58.7, -0.3, 0.1, 0.002, -0.001)),
    ("FULL_OPENCV", (120.0, 118.0, 81.3, 58.7, -0.28, 0.09, 0.001, 0.001, -0.02, 0.01, 0.0, 0.0)),
])
def test_undistortion_gives_the_pinhole_image_of_the_lens(model: str, params: tuple[float, ...]) -> None:
    # a photo through the lens of a smooth pattern on the normalised image plane, made with
    # OpenCV's own model; undistorted, each pixel must show the pattern where its pinhole ray is
    w, h = 160, 120
    f2 = params[1] if model in ("OPENCV", "FULL_OPENCV") else params[0]
    off = 2 if model in ("OPENCV", "FULL_OPENCV") else 1
    cam = Camera(params[0], f2, params[off], params[off + 1], w, h, np.eye(4))
    dist = colmap_distortion(model, params, "test")
    assert dist is not None
    k = cam.K.copy()
    k[:2, 2] -= 0.5
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    n = cv2.undistortPoints(np.stack([u.ravel() - 0.5, v.ravel() - 0.5], 1).reshape(-1, 1, 2), k,
                            np.asarray(dist.coeffs)).reshape(h, w, 2)
    photo = np.rint(_pattern(n[..., 0], n[..., 1]) * 255).astype(np.uint8)
    out, c2 = undistort(photo, cam, dist)
    assert out.shape == (c2.height, c2.width) and c2.width <= w and c2.height <= h
    u2, v2 = np.meshgrid(np.arange(c2.width) + 0.5, np.arange(c2.height) + 0.5)

    def psnr(a: np.ndarray, b: np.ndarray) -> float:
        return float(-10 * np.log10(np.mean(((a.astype(np.float64) - b) / 255) ** 2)))

    assert psnr(out, _pattern((u2 - c2.cx) / c2.fx, (v2 - c2.cy) / c2.fy) * 255) > 45
    # the photo as it is does not match its pinhole camera: undistortion is what fixed it
    assert psnr(photo, _pattern((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy) * 255) < 30


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    return room()


def _sizes_capture(root: Path, scene, sizes: list[tuple[int, int]], *, binary: bool = True) -> Path:  # type: ignore[no-untyped-def]
    poses = orbit_poses(len(sizes))
    shots = [Shot(f"im_{i:03d}.png", pinhole(w2c, w, h)) for i, (w2c, (w, h)) in enumerate(zip(poses, sizes))]
    return write_capture(root, scene, shots, binary=binary, points=300)


def test_colmap_undistorted_layout_every_image_its_own_size_fits_through_the_cli(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    sizes = [(64, 42), (64, 43), (63, 42), (64, 44), (62, 42), (64, 41), (63, 43), (64, 42), (64, 40)]
    root = _sizes_capture(tmp_path / "undist", scene, sizes)
    with pytest.raises(CaptureError, match="9 different image sizes|different image sizes"):
        trajectory.from_colmap(root)  # one Cameras path needs one size: a typed error saying so
    views = trajectory.read_colmap_views(root)
    assert [(v.camera.width, v.camera.height) for v in views] == sizes
    cfg = tmp_path / "cfg.toml"
    from morphgs.fit import FitConfig

    cfg.write_text(FitConfig.from_dict(small_config(30)).to_toml())
    r = _cli("fit", str(root), "--out", str(tmp_path / "run"), "--config", str(cfg), "--no-progress")
    assert r.returncode == 0, r.stderr
    cams = json.loads((tmp_path / "run" / "cameras.json").read_text())
    got = {c["img_name"]: (c["width"], c["height"]) for c in cams}
    assert got == {f"im_{i:03d}": s for i, s in enumerate(sizes)}
    summary = json.loads((tmp_path / "run" / "fit.json").read_text())
    assert summary["steps"] == 30 and summary["heldout_psnr"] is not None


def test_mixed_portrait_and_landscape_cameras(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    sizes = [(64, 48), (48, 64)] * 4
    root = _sizes_capture(tmp_path / "phone", scene, sizes, binary=False)
    res = fit(root, tmp_path / "run", config=small_config(20), progress=False)
    assert res.steps == 20 and res.heldout_psnr is not None
    # a render path at one size of another aspect (16:9): every camera is scaled uniformly and
    # centre-cropped, not stretched (square pixels, the centre of the photo stays the centre of the
    # frame); the landscape 4:3 ones are said, with a size that keeps the whole view
    with pytest.warns(morphgs.MorphgsWarning, match=r"64x48 .* keeping 75 % of the view.* --size 72x54"):
        cams = trajectory.from_colmap(root, resolution=(96, 54))
    views = trajectory.read_colmap_views(root)
    for c, v in zip(cams, views):
        assert (c.width, c.height) == (96, 54)
        assert c.fx == pytest.approx(c.fy)
        assert c.fx == pytest.approx(v.camera.fx * (96 / 48 if v.camera.width < v.camera.height else 96 / 64))
        np.testing.assert_allclose(c.project([c.center + c.camera_to_world[:3, 2]]), [[48.0, 27.0]], atol=1e-9)


def _distorted_colmap(root: Path, scene, model: str, coeffs: tuple[float, ...], n: int = 8) -> Path:  # type: ignore[no-untyped-def]
    shots = []
    for i, w2c in enumerate(orbit_poses(n)):
        c = pinhole(w2c, 64, 48)
        if model in ("SIMPLE_RADIAL", "RADIAL", "SIMPLE_PINHOLE", "OPENCV_FISHEYE") and model != "OPENCV_FISHEYE":
            params = (c.fx, c.cx, c.cy, *coeffs)
        else:
            params = (c.fx, c.fy, c.cx, c.cy, *coeffs)
        shots.append(Shot(f"im_{i:03d}.png", c, model, params))
    return write_capture(root, scene, shots)


def test_distorted_colmap_capture_is_undistorted_into_the_run_folder(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    root = _distorted_colmap(tmp_path / "opencv", scene, "OPENCV", (-0.3, 0.1, 0.002, -0.001))
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    res = fit(root, tmp_path / "run", config=small_config(20), progress=False)
    cache = tmp_path / "run" / "undistorted"
    files = sorted(cache.glob("*.png"))
    assert len(files) == 8  # every view, train and held out
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before  # nothing written beside the data
    cams = json.loads((tmp_path / "run" / "cameras.json").read_text())
    assert all(c["width"] < 64 and c["height"] < 48 for c in cams)  # cropped to the valid region
    mtimes = [p.stat().st_mtime_ns for p in files]
    res2 = fit(root, tmp_path / "run", config=small_config(20), progress=False)  # finished: nothing to redo
    assert [p.stat().st_mtime_ns for p in files] == mtimes and res2.steps == res.steps
    posed = load_posed_images(root)
    imgs, ucams, _ = posed.read([0], cache=cache)
    assert imgs[0].shape[:2] == (ucams[0].height, ucams[0].width)


def test_transforms_json_distortion_is_undistorted(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    cams = [pinhole(w2c, 64, 48) for w2c in orbit_poses(6)]
    root = write_transforms(tmp_path / "ns", scene, cams, distortion={"k1": -0.25, "k2": 0.05, "p1": 0.001, "p2": 0.0})
    posed = load_posed_images(root)
    assert all(d is not None and d.coeffs == (-0.25, 0.05, 0.001, 0.0) for d in posed.distortion or [])
    imgs, ucams, _ = posed.read([0, 3])
    for im, c in zip(imgs, ucams):
        assert im.shape[:2] == (c.height, c.width) and (c.width, c.height) != (64, 48)


@pytest.mark.parametrize("layout", ["colmap_fisheye", "transforms_fisheye", "transforms_k4"])
def test_fisheye_and_unsupported_lenses_are_refused_through_the_cli(scene, tmp_path: Path, layout: str) -> None:  # type: ignore[no-untyped-def]
    if layout == "colmap_fisheye":
        root = tmp_path / "fe"
        shots = [Shot(f"im_{i}.png", pinhole(w2c, 32, 24), "OPENCV_FISHEYE", (30.0, 30.0, 16.0, 12.0, 0.1, 0.0, 0.0, 0.0))
                 for i, w2c in enumerate(orbit_poses(3))]
        (root / "images").mkdir(parents=True)
        write_colmap(root / "sparse" / "0", shots)
        needles = ("OPENCV_FISHEYE", "fisheye", "image_undistorter")
    else:
        cams = [pinhole(w2c, 32, 24) for w2c in orbit_poses(3)]
        extra = {"camera_model": "OPENCV_FISHEYE"} if layout == "transforms_fisheye" else {"k4": 0.01}
        root = write_transforms(tmp_path / "ns", scene, cams, distortion={"k1": 0.1}, extra=extra)
        needles = ("transforms.json", "frames[0]", "OPENCV_FISHEYE") if layout == "transforms_fisheye" else ("k4",)
    _one_line_error(_cli("fit", str(root), "--out", str(tmp_path / "run"), "--no-progress", "--steps", "5"), *needles)


def test_bad_capture_layouts_are_one_line_cli_errors(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    cams = [pinhole(w2c, 32, 24) for w2c in orbit_poses(3)]
    # an image that is not a rescale of its camera (per-image sizes do not excuse that)
    root = write_transforms(tmp_path / "a", scene, cams)
    from PIL import Image

    Image.new("RGB", (30, 30)).save(root / "images" / "frame_00001.png")
    _one_line_error(_cli("fit", str(root), "--out", str(tmp_path / "r1"), "--steps", "5"), "frame_00001.png", "30x30", "32x24")
    # a camera model COLMAP does not define
    m = tmp_path / "b" / "sparse" / "0"
    write_colmap(m, [Shot("x.png", cams[0])], binary=False)
    (m / "cameras.txt").write_text("1 WEIRD 32 24 1 2 3\n")
    _one_line_error(_cli("fit", str(tmp_path / "b"), "--out", str(tmp_path / "r2"), "--steps", "5"), "cameras.txt", "WEIRD")
    # an image referring to a camera that is not defined
    (m / "cameras.txt").write_text("7 PINHOLE 32 24 30 30 16 12\n")
    _one_line_error(_cli("fit", str(tmp_path / "b"), "--out", str(tmp_path / "r3"), "--steps", "5"), "camera 1", "not defined")
    # a registered image whose file is missing
    m2 = tmp_path / "c" / "sparse" / "0"
    (tmp_path / "c" / "images").mkdir(parents=True)
    write_colmap(m2, [Shot("x.png", cams[0], "OPENCV", (30.0, 30.0, 16.0, 12.0, -0.1, 0.0, 0.0, 0.0))])
    r = _cli("fit", str(tmp_path / "c"), "--out", str(tmp_path / "r4"), "--holdout", "none", "--steps", "5")
    _one_line_error(r, "x.png", "missing")


def test_fit_data_error_is_a_capture_error_and_a_value_error() -> None:
    assert issubclass(FitDataError, CaptureError) and issubclass(CaptureError, ValueError)


def test_sparse_pairs_from_a_mixed_orientation_capture_keep_each_photo_as_it_is(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    import morphgs
    from morphgs.curation import curate, load_manifest

    sizes = [(64, 48), (48, 64), (64, 47), (47, 64)] * 3
    root = _sizes_capture(tmp_path / "phone", scene, sizes)
    morphgs.save_ply(scene, root / "scene.ply")
    out = tmp_path / "data"
    s = curate([root], out, configs=["sparse-n:4@20"], pairs_per_scene=1, frames=4, resolution=(64, 48),
               progress=False, log=lambda m: None)
    assert s.ok, s.failed
    (rec,) = load_manifest(out).values()
    assert rec["fit"]["images"] == "images"
    meta = json.loads((out / rec["fit"]["dir"] / "data" / "transforms.json").read_text())
    got = sorted({(f["w"], f["h"]) for f in meta["frames"]})
    assert (48, 64) in got and (64, 48) in got  # portrait photos stay portrait, nothing stretched


def _masked_capture(root: Path, scene, garbage_seed: int) -> tuple[Path, list[np.ndarray]]:  # type: ignore[no-untyped-def]
    """A transforms.json capture whose photos hold a 'passer-by' (noise of `garbage_seed`) in a
    masked box."""
    from PIL import Image

    cams = [pinhole(w2c, 48, 36) for w2c in orbit_poses(9)]
    masks = []
    for i in range(len(cams)):
        m = np.ones((36, 48), bool)
        m[6 + i:22 + i, 10 + 2 * i:26 + 2 * i] = False
        masks.append(m)
    root = write_transforms(root, scene, cams, masks=masks)
    rng = np.random.default_rng(garbage_seed)
    for i, m in enumerate(masks):
        p = root / "images" / f"frame_{i:05d}.png"
        img = np.asarray(Image.open(p)).copy()
        img[~m] = rng.integers(0, 256, size=(int((~m).sum()), 3), dtype=np.uint8)
        Image.fromarray(img).save(p)
    return root, masks


def test_masked_pixels_are_out_of_the_loss_and_the_heldout_metrics(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    import morphgs

    cfg = small_config(25, output={"eval_every": 0, "checkpoint_every": 100, "preview_every": 0,
                                   "progress_every": 0.0, "lpips": "off"})
    a, masks = _masked_capture(tmp_path / "a", scene, 1)
    b, _ = _masked_capture(tmp_path / "b", scene, 2)
    ra = fit(a, tmp_path / "ra", config=cfg, progress=False)
    rb = fit(b, tmp_path / "rb", config=cfg, progress=False)
    # the photos differ only under the masks: the fits are the same bytes
    assert ra.ply.read_bytes() == rb.ply.read_bytes()
    assert ra.heldout_psnr == rb.heldout_psnr
    # without the masks the passer-by is learnt
    import shutil

    c = tmp_path / "c"
    shutil.copytree(b, c)
    meta = json.loads((c / "transforms.json").read_text())
    for fr in meta["frames"]:
        del fr["mask_path"]
    shutil.rmtree(c / "masks")
    (c / "transforms.json").write_text(json.dumps(meta))
    rc = fit(c, tmp_path / "rc", config=cfg, progress=False)
    assert rc.ply.read_bytes() != rb.ply.read_bytes()
    # held-out PSNR is over the kept pixels only
    posed = load_posed_images(a)
    imgs, cams, ms = posed.read(ra.heldout_views)
    vals = []
    for im, cam, m in zip(imgs, cams, ms):
        assert m is not None
        r = np.clip(np.asarray(morphgs.render(ra.scene, cam).rgb), 0, 1)
        d = (r - im.astype(np.float32) / 255.0)[m]
        vals.append(-10 * np.log10(np.mean(d.astype(np.float64) ** 2)))
    assert ra.heldout_psnr == pytest.approx(float(np.mean(vals)), abs=1e-3)


def test_masks_folder_of_a_colmap_capture_and_a_missing_mask(scene, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from PIL import Image

    root = _sizes_capture(tmp_path / "cm", scene, [(40, 30)] * 4)
    (root / "masks").mkdir()
    for i in range(3):
        m = np.full((30, 40), 255, np.uint8)
        m[:10] = 0
        Image.fromarray(m).save(root / "masks" / f"im_{i:03d}.png.png")  # COLMAP's NAME.png
    _one_line_error(_cli("fit", str(root), "--out", str(tmp_path / "r"), "--steps", "5"), "masks", "im_003.png")
    Image.fromarray(np.zeros((30, 40), np.uint8)).save(root / "masks" / "im_003.png")  # masks everything
    _one_line_error(_cli("fit", str(root), "--out", str(tmp_path / "r"), "--steps", "5"), "im_003.png", "no pixel")
    Image.fromarray(np.full((30, 40), 255, np.uint8)).save(root / "masks" / "im_003.png")
    posed = load_posed_images(root)
    _, _, ms = posed.read([0, 3])
    assert ms[0] is not None and not ms[0][:10].any() and ms[0][10:].all()
    assert ms[1] is None  # an all-kept mask is no mask
