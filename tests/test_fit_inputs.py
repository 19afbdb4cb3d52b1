"""`morphgs fit` inputs: COLMAP datasets, point-cloud and scene initialisation, the config file,
view selection, and bad inputs (each a clear MorphgsError naming the file or field)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fit_helpers import make_dataset, small_config, write_point_ply
from morphgs.fit import (
    FitConfig,
    FitConfigError,
    FitDataError,
    InitError,
    ViewSelectionError,
    fit,
    load_posed_images,
    read_points,
    select_views,
)
from morphgs.trajectory._rotations import matrix_to_quat


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root, _, _ = make_dataset(tmp_path_factory.mktemp("fitin") / "room", views=12, points=600)
    return root


def _colmap_copy(src: Path, dst: Path, *, points: int = 300) -> Path:
    """The dataset as a COLMAP text model (sparse/0) + images/ + points3D.txt."""
    posed = load_posed_images(src)
    (dst / "sparse" / "0").mkdir(parents=True)
    shutil.copytree(src / "images", dst / "images")
    c0 = posed.cameras[0]
    (dst / "sparse/0/cameras.txt").write_text(
        f"# camera list\n1 PINHOLE {c0.width} {c0.height} {c0.fx} {c0.fy} {c0.cx} {c0.cy}\n")
    lines = []
    for i, (cam, p) in enumerate(zip(posed.cameras, posed.paths)):
        q = matrix_to_quat(cam.world_to_camera[:3, :3])
        t = cam.world_to_camera[:3, 3]
        lines += [f"{i + 1} {' '.join(map(repr, q.tolist()))} {' '.join(map(repr, t.tolist()))} 1 {p.name}", ""]
    (dst / "sparse/0/images.txt").write_text("\n".join(lines) + "\n")
    pts, cols = read_points(src / "points.ply")
    rows = [f"{i + 1} {x!r} {y!r} {z!r} {int(r * 255)} {int(g * 255)} {int(b * 255)} 0.5 1 0"
            for i, ((x, y, z), (r, g, b)) in enumerate(zip(pts[:points].tolist(), cols[:points].tolist()))]
    (dst / "sparse/0/points3D.txt").write_text("# points\n" + "\n".join(rows) + "\n")
    return dst


def test_colmap_dataset_with_points3d_init_trains(dataset: Path, tmp_path: Path) -> None:
    data = _colmap_copy(dataset, tmp_path / "colmap")
    posed = load_posed_images(data)
    assert len(posed) == 12 and posed.points == data / "sparse/0/points3D.txt"
    ref = load_posed_images(dataset)
    np.testing.assert_allclose(np.stack([c.world_to_camera for c in posed.cameras]),
                               np.stack([c.world_to_camera for c in ref.cameras]), atol=1e-9)
    res = fit(data, tmp_path / "run", config=small_config(150), progress=False)
    assert "points3D.txt" in res.summary["init"]
    assert res.heldout_psnr is not None and res.heldout_psnr > 18.0


def test_point_cloud_ply_and_scene_init(dataset: Path, tmp_path: Path) -> None:
    pts, cols = read_points(dataset / "points.ply")
    assert pts.shape == (600, 3) and cols.min() >= 0 and cols.max() <= 1
    res = fit(dataset, tmp_path / "a", config=small_config(20), init=f"ply:{dataset / 'points.ply'}", progress=False)
    assert res.summary["init"].startswith("point cloud")
    # an existing scene continues training from its Gaussians
    res2 = fit(dataset, tmp_path / "b", config=small_config(20), init=f"scene:{res.ply}", progress=False)
    assert res2.summary["init"].startswith("scene")
    # an ASCII PLY with double coordinates and no colours
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
                         "property double z\nend_header\n0 0 0\n1 2 3\n")
    p, c = read_points(ascii_ply)
    np.testing.assert_array_equal(p, [[0, 0, 0], [1, 2, 3]])
    np.testing.assert_array_equal(c, np.full((2, 3), 0.5, np.float32))


def test_missing_image_names_the_file(dataset: Path, tmp_path: Path) -> None:
    data = tmp_path / "d"
    shutil.copytree(dataset, data)
    (data / "images" / "frame_00005.png").unlink()
    with pytest.raises(FileNotFoundError, match="frame_00005.png"):
        fit(data, tmp_path / "run", config=small_config(10), progress=False)


def test_image_whose_size_disagrees_with_its_camera(dataset: Path, tmp_path: Path) -> None:
    from PIL import Image

    data = tmp_path / "d"
    shutil.copytree(dataset, data)
    Image.new("RGB", (50, 48)).save(data / "images" / "frame_00003.png")
    with pytest.raises(FitDataError, match=r"frame_00003.png: image is 50x48, but its camera is 64x48"):
        fit(data, tmp_path / "run", config=small_config(10), progress=False)
    # a uniform downscale (an images_2 folder) is accepted and the cameras follow
    (data / "images_2").mkdir()
    for p in sorted((dataset / "images").iterdir()):
        Image.open(p).resize((32, 24)).save(data / "images_2" / p.name)
    res = fit(data, tmp_path / "run2", config=small_config(10), images="images_2", progress=False)
    assert json.loads((res.run_dir / "cameras.json").read_text())[0]["width"] == 32


def test_selection_that_leaves_no_training_view(dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ViewSelectionError, match="leaves no training view"):
        fit(dataset, tmp_path / "run", config=small_config(10), views="n:1", holdout="0,1,2,3,4,5,6,7,8,9,10,11",
            progress=False)
    with pytest.raises(ViewSelectionError, match="out of range"):
        select_views(12, [3, 40])
    with pytest.raises(ViewSelectionError, match="every:K needs"):
        select_views(12, "every:x")
    sel = select_views(12, "0,3", holdout="every:8")
    assert sel.train == [0, 3] and sel.heldout == [8]


def test_empty_initialisation(dataset: Path, tmp_path: Path) -> None:
    empty = tmp_path / "empty.ply"
    write_point_ply(empty, np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(InitError, match="empty initialisation"):
        fit(dataset, tmp_path / "run", config=small_config(10), init=f"ply:{empty}", progress=False)
    with pytest.raises(InitError, match="random:N"):
        fit(dataset, tmp_path / "run", config=small_config(10), init="random:lots", progress=False)
    no_points = tmp_path / "np"
    shutil.copytree(dataset, no_points)
    meta = json.loads((no_points / "transforms.json").read_text())
    del meta["ply_file_path"]
    (no_points / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InitError, match="no point cloud"):
        fit(no_points, tmp_path / "run", config=small_config(10), init="points", progress=False)


def test_lying_point_cloud_header_is_refused_before_allocating(tmp_path: Path) -> None:
    p = tmp_path / "liar.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
                  b"property float y\nproperty float z\nend_header\n" + b"\0" * 24)
    with pytest.raises(FitDataError, match="4000000000 vertices declared"):
        read_points(p)
    b = tmp_path / "points3D.bin"
    b.write_bytes((10**12).to_bytes(8, "little") + b"\0" * 40)
    with pytest.raises(FitDataError, match="claims"):
        read_points(b)


def test_config_file_round_trip_and_errors(tmp_path: Path) -> None:
    cfg = FitConfig.preset("sparse")
    path = tmp_path / "c.toml"
    path.write_text(cfg.to_toml())
    assert FitConfig.load(path) == cfg
    path.write_text("steps = 100\n[default]\nopacity_reset = false\n")
    c = FitConfig.load(path)
    assert c.steps == 100 and not c.default.opacity_reset and c.lr.means == 1.6e-4
    for text, field in [("stepz = 3\n", "stepz"), ("[default]\ngrow_grad2d = 'x'\n", "default.grow_grad2d"),
                        ("[lr]\nmeans = -1.0\n", "lr.means"), ("strategy = 'adc'\n", "strategy"),
                        ("steps = [\n", "not valid TOML")]:
        path.write_text(text)
        with pytest.raises(FitConfigError, match=field.replace(".", r"\.")):
            FitConfig.load(path)


def test_cli_prints_the_pinned_defaults_and_refuses_bad_arguments(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "morphgs.cli", "fit", "--print-config"], capture_output=True,
                         text=True, check=True).stdout
    from morphgs.fit.config import _toml_loads

    cfg = FitConfig.from_dict(_toml_loads(out))
    assert cfg == FitConfig()
    assert "means = 0.00016" in out and "opacity_reset = true" in out
    r = subprocess.run([sys.executable, "-m", "morphgs.cli", "fit", str(tmp_path / "nothing"), "--out",
                        str(tmp_path / "run")], capture_output=True, text=True)
    assert r.returncode == 1 and "nothing: no such file or folder" in r.stderr


def test_fit_does_not_import_torch() -> None:
    code = "import sys, morphgs.fit, morphgs.commands.fit; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
