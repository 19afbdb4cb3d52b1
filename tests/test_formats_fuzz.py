"""Every scene reader, fed real files cut short or with bytes changed, either loads a valid scene
or raises SceneFormatError naming the file: never a panic, another exception type, a hang or a
huge allocation (hypothesis picks the damage; the files are the fixtures from other tools and
files written by morphgs.save)."""

from __future__ import annotations

import io
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import morphgs

FORMATS = {
    "spz-v2": "splat-transform_minimal-v2.spz",
    "spz-v3": "metalsplatter_train3.spz",
    "spz-v4": "splat-transform_minimal-v4.spz",
    "splat": "marcelpadilla_spot_10k.splat",
    "compressed-ply": "playcanvas_engine_guitar.compressed.ply",
    "sog": "playcanvas_engine_monkey_0001.sog",
    "ply": "splatapult_test.ply",
}

# a damaged file: cut at some fraction of its length, then up to 8 bytes overwritten
damage = st.tuples(
    st.floats(min_value=0.0, max_value=1.0),
    st.lists(st.tuples(st.floats(min_value=0.0, max_value=1.0), st.integers(0, 255)), max_size=8),
)


def _damaged(data: bytes, cut: float, edits: list[tuple[float, int]]) -> bytes:
    b = bytearray(data[: max(1, int(len(data) * cut))] if cut < 1.0 else data)
    for where, value in edits:
        b[min(len(b) - 1, int(len(b) * where))] = value
    return bytes(b)


def _load_or_format_error(path: Path) -> None:
    try:
        with warnings.catch_warnings():
            # a damaged file may load with a note (e.g. a SCALE read as log-space)
            warnings.simplefilter("ignore", morphgs.MorphgsWarning)
            scene = morphgs.load(path)
    except morphgs.SceneFormatError as e:
        assert str(path) in str(e), e
        return
    # what loads is a usable scene: finite values, unit quaternions, opacities in [0, 1]
    assert np.isfinite(np.asarray(scene.means)).all()
    q = np.asarray(scene.quats)
    if len(q):
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-4)


def _glb_bytes(tmp: Path) -> bytes:
    scene = morphgs.synthetic.scene(300, sh_degree=2, seed=3)
    p = tmp / "src.glb"
    morphgs.save(scene, p)
    return p.read_bytes()


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_damaged_files_load_or_raise_scene_format_error(fmt: str, fixtures_dir: Path,
                                                        tmp_path_factory: pytest.TempPathFactory) -> None:
    name = FORMATS[fmt]
    data = (fixtures_dir / name).read_bytes()
    tmp = tmp_path_factory.mktemp(fmt)
    suffix = "".join(Path(name).suffixes[-2:]) if name.endswith(".compressed.ply") else Path(name).suffix

    @settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(damage)
    def check(d: tuple[float, list[tuple[float, int]]]) -> None:
        p = tmp / f"damaged{suffix}"
        p.write_bytes(_damaged(data, *d))
        _load_or_format_error(p)

    check()


def test_damaged_glb_files_load_or_raise(tmp_path: Path) -> None:
    data = _glb_bytes(tmp_path)

    @settings(max_examples=60, deadline=None, derandomize=True)
    @given(damage)
    def check(d: tuple[float, list[tuple[float, int]]]) -> None:
        p = tmp_path / "damaged.glb"
        p.write_bytes(_damaged(data, *d))
        _load_or_format_error(p)

    check()


def test_sog_with_damaged_members_loads_or_raises(fixtures_dir: Path, tmp_path: Path) -> None:
    """The zip container intact, one member (meta.json or a WebP texture) damaged inside it."""
    src = zipfile.ZipFile(fixtures_dir / FORMATS["sog"])
    members = {i.filename: src.read(i.filename) for i in src.infolist()}

    @settings(max_examples=60, deadline=None, derandomize=True)
    @given(st.sampled_from(sorted(members)), damage)
    def check(member: str, d: tuple[float, list[tuple[float, int]]]) -> None:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            for k, v in members.items():
                z.writestr(k, _damaged(v, *d) if k == member else v)
        p = tmp_path / "member.sog"
        p.write_bytes(buf.getvalue())
        _load_or_format_error(p)

    check()


def test_scenesplat_folders_with_a_damaged_array_load_or_raise(fixtures_dir: Path, tmp_path: Path) -> None:
    from test_formats_scenesplat import _preprocess_gs

    src = tmp_path / "src"
    _preprocess_gs(morphgs.load(fixtures_dir / "splatapult_test.ply"), src)
    arrays = {p.name: p.read_bytes() for p in src.glob("*.npy")}

    @settings(max_examples=60, deadline=None, derandomize=True)
    @given(st.sampled_from(sorted(arrays)), damage)
    def check(member: str, d: tuple[float, list[tuple[float, int]]]) -> None:
        folder = tmp_path / "damaged"
        folder.mkdir(exist_ok=True)
        for k, v in arrays.items():
            (folder / k).write_bytes(_damaged(v, *d) if k == member else v)
        try:
            morphgs.load(folder)
        except morphgs.SceneFormatError as e:
            assert str(folder) in str(e), e

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", morphgs.MorphgsWarning)  # the lossy-colour note of each load
        check()
