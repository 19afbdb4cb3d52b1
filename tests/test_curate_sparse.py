"""`morphgs curate --config sparse:K / sparse-n:N`: pairs whose corrupted side is a real
sparse-view reconstruction, in the same manifest and layout, with one cached fit per scene."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

import morphgs
from morphgs import MorphgsWarning
from fit_helpers import make_dataset
from morphgs.curation import curate, load_manifest, parse_config


def test_parse_sparse_configs(tmp_path: Path) -> None:
    c = parse_config("sparse:8")
    assert (c.label, c.kind, c.params) == ("sparse-8", "sparse", {"every": 8})
    c = parse_config("sparse-n:3@500")
    assert (c.label, c.params) == ("sparse-n3-500steps", {"n": 3, "steps": 500})
    for bad in ("sparse:0", "sparse:x", "sparse-n:2@-5"):
        with pytest.raises(ValueError, match="sparse"):
            parse_config(bad)
    f = tmp_path / "s20.json"
    f.write_text(json.dumps({"kind": "sparse", "every": 20, "steps": 100, "fit": {"strategy": "default"}}))
    c = parse_config(str(f))
    assert (c.label, c.params) == ("s20", {"every": 20, "steps": 100, "fit": {"strategy": "default"}})
    f.write_text(json.dumps({"kind": "sparse", "every": 2, "n": 3}))
    with pytest.raises(ValueError, match="exactly one"):
        parse_config(str(f))


def test_sparse_pairs_share_one_cached_fit_and_resume(tmp_path: Path) -> None:
    out = tmp_path / "data"
    kw = dict(configs=["sparse:16@60", "morphological"], pairs_per_scene=2, frames=4, resolution=(64, 48),
              builtin_scenes=1, builtin_gaussians=3000, progress=False, log=lambda m: None)
    s = curate([], out, **kw)
    assert s.ok and s.done == 4
    man = load_manifest(out)
    sparse = [r for r in man.values() if r["config"]["kind"] == "sparse"]
    assert len(sparse) == 2
    dirs = {r["fit"]["dir"] for r in sparse}
    assert len(dirs) == 1 and len(list((out / "fits" / "sample-0").iterdir())) == 1
    info = sparse[0]["fit"]
    assert info["train_views"] == list(range(0, 96, 16)) and info["images"] == "renders" and info["steps"] == 60
    assert info["heldout_psnr"] is not None
    # the corrupted frames are renders of the fitted scene along the pair's path
    rec = sparse[0]
    fitted = morphgs.load(out / info["ply"])
    cams = morphgs.Cameras.from_dict(json.loads((out / rec["paths"]["cameras"]).read_text()))
    want = morphgs.render(fitted, cams).to_uint8()
    got = np.stack([np.asarray(Image.open(out / rec["paths"]["corrupted"] / f"{i:05d}.png")) for i in range(4)])
    np.testing.assert_array_equal(got, want)
    clean = np.stack([np.asarray(Image.open(out / rec["paths"]["clean"] / f"{i:05d}.png")) for i in range(4)])
    assert np.abs(clean.astype(int) - got.astype(int)).mean() > 2
    # a rerun makes nothing and does not refit
    stamp = (out / info["dir"] / "run" / "fit.json").stat().st_mtime_ns
    s2 = curate([], out, **kw)
    assert s2.done == 0 and s2.skipped == 4
    assert (out / info["dir"] / "run" / "fit.json").stat().st_mtime_ns == stamp
    # a lost pair is remade from the cached fit, to the same bytes
    import shutil

    first = np.asarray(Image.open(out / rec["paths"]["corrupted"] / "00000.png"))
    shutil.rmtree(out / rec["paths"]["dir"])
    s3 = curate([], out, **kw)
    assert s3.done == 1
    np.testing.assert_array_equal(np.asarray(Image.open(out / rec["paths"]["corrupted"] / "00000.png")), first)


def test_scene_folder_with_images_fits_the_real_images(tmp_path: Path) -> None:
    root, scene, cams = make_dataset(tmp_path / "room", views=16, size=(64, 48), gaussians=3000)
    morphgs.save_ply(scene, root / "scene.ply")
    out = tmp_path / "data"
    s = curate([root], out, configs=["sparse-n:4@40"], pairs_per_scene=1, frames=4, resolution=(64, 48),
               progress=False, log=lambda m: None)
    assert s.ok, s.failed
    (rec,) = load_manifest(out).values()
    info = rec["fit"]
    assert info["images"] == "images" and info["capture_views"] == 16
    assert info["train_views"] == [0, 5, 10, 15]
    # the fit's first training image is the scene folder's frame 0
    fitted = out / info["dir"] / "data" / "images" / "view_00000.png"
    np.testing.assert_array_equal(np.asarray(Image.open(fitted)),
                                  np.asarray(Image.open(root / "images" / "frame_00000.png")))


def test_a_fit_run_folder_fits_the_photos_of_its_capture(tmp_path: Path) -> None:
    """`morphgs curate RUN --config sparse:K` on a `morphgs fit` run: the sparse fit trains on the
    photos the run was fitted from (found through views.json), not on renders of the dense fit;
    renders again when the capture has moved."""
    import shutil

    from fit_helpers import small_config
    from morphgs.fit import fit

    root, _, _ = make_dataset(tmp_path / "room", views=16, size=(64, 48), gaussians=3000)
    for p in sorted((root / "images").iterdir()):  # photos that no render of the scene gives
        Image.fromarray(255 - np.asarray(Image.open(p))).save(p)
    res = fit(root, tmp_path / "run", config=small_config(20), progress=False)
    out = tmp_path / "data"
    kw: dict[str, Any] = dict(configs=["sparse-n:4@40"], pairs_per_scene=1, frames=4, resolution=(64, 48), progress=False,
              log=lambda m: None)
    s = curate([res.run_dir], out, **kw)
    assert s.ok, s.failed
    (rec,) = load_manifest(out).values()
    info = rec["fit"]
    assert info["images"] == "images" and info["capture_views"] == 16 and info["train_views"] == [0, 5, 10, 15]
    for k, view in enumerate(info["train_views"]):
        fitted = np.asarray(Image.open(out / info["dir"] / "data" / "images" / f"view_{k:05d}.png"))
        np.testing.assert_array_equal(fitted, np.asarray(Image.open(root / "images" / f"frame_{view:05d}.png")))
    shutil.move(root, tmp_path / "moved")
    with pytest.warns(MorphgsWarning, match=r"views\.json: the capture it names, .*room.*, cannot be read.*"
                      r"trains on renders"):
        s2 = curate([res.run_dir], tmp_path / "data2", **kw)
    assert s2.ok, s2.failed
    (rec2,) = load_manifest(tmp_path / "data2").values()
    assert rec2["fit"]["images"] == "renders"
    (res.run_dir / "views.json").write_text('{"source": ', encoding="utf-8")  # damaged
    with pytest.warns(MorphgsWarning, match=r"views\.json: unreadable .*trains on renders"):
        s3 = curate([res.run_dir], tmp_path / "data3", **kw)
    assert s3.ok and load_manifest(tmp_path / "data3").popitem()[1]["fit"]["images"] == "renders"


def test_an_inria_output_folder_fits_the_photos_its_cfg_args_names(tmp_path: Path) -> None:
    """The INRIA trainer's output folder (cameras.json, cfg_args, point_cloud/iteration_N/): the
    sparse fit trains on the photos of the COLMAP/transforms capture that cfg_args'
    `source_path` names (relative to where the trainer ran, as INRIA's train.py writes it), and says so when one is missing."""
    import shutil

    from fit_helpers import small_config
    from morphgs.fit import fit

    root, _, _ = make_dataset(tmp_path / "scenes" / "room", views=12, size=(64, 48), gaussians=3000)
    for p in sorted((root / "images").iterdir()):
        Image.fromarray(255 - np.asarray(Image.open(p))).save(p)
    res = fit(root, tmp_path / "run", config=small_config(20), progress=False)
    model = tmp_path / "output" / "3f2a9c1d-0"
    (model / "point_cloud" / "iteration_20").mkdir(parents=True)
    shutil.copy(next(res.run_dir.glob("point_cloud/iteration_*/point_cloud.ply")),
                model / "point_cloud" / "iteration_20" / "point_cloud.ply")
    shutil.copy(res.run_dir / "cameras.json", model / "cameras.json")
    (model / "cfg_args").write_text(
        "Namespace(data_device='cuda', eval=False, images='images', model_path='./output/3f2a9c1d-0', "
        "resolution=-1, sh_degree=3, source_path='scenes/room', white_background=False)", encoding="utf-8")
    kw: dict[str, Any] = dict(configs=["sparse-n:3@30"], pairs_per_scene=1, frames=3, resolution=(64, 48), progress=False,
              log=lambda m: None)
    s = curate([model], tmp_path / "data", **kw)
    assert s.ok, s.failed
    (rec,) = load_manifest(tmp_path / "data").values()
    info = rec["fit"]
    assert info["images"] == "images" and info["capture_views"] == 12
    for k, view in enumerate(info["train_views"]):
        fitted = np.asarray(Image.open(tmp_path / "data" / info["dir"] / "data" / "images" / f"view_{k:05d}.png"))
        np.testing.assert_array_equal(fitted, np.asarray(Image.open(root / "images" / f"frame_{view:05d}.png")))
    (root / "images" / "frame_00004.png").unlink()
    with pytest.warns(MorphgsWarning, match=r"cfg_args: the capture it names, .*room.*, (has no photo for 1 of its 12|"
                                            r"cannot be read).*trains on renders"):
        s2 = curate([model], tmp_path / "data2", **kw)
    assert s2.ok and load_manifest(tmp_path / "data2").popitem()[1]["fit"]["images"] == "renders"
