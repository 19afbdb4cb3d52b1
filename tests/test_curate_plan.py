"""Curation planning: seeds, splits, sharding, scene discovery, manifest handling (no rendering)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from morphgs.cli import main
from morphgs.curation import builtin_sources, discover, pair_seed, scene_split
from morphgs.curation import manifest
from morphgs.curation.plan import ConfigSpec, make_plan

CFG_A = ConfigSpec("a", "blur2d", {"sigma": 1.0})
CFG_B = ConfigSpec("b", "blur2d", {"sigma": 2.0})


def test_pair_seed_is_the_documented_sha256_formula() -> None:
    text = "morphgs/pair-seed/v1\0" + "7\0" + "garden\0" + "3"
    expected = int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1
    assert pair_seed(7, "garden", 3) == expected
    assert 0 <= expected < 2**63


def test_pair_seeds_differ_across_run_seed_scene_and_index() -> None:
    seeds = {pair_seed(r, s, k) for r in (0, 1) for s in ("a", "b", "ab") for k in range(20)}
    assert len(seeds) == 2 * 3 * 20


def test_split_is_deterministic_by_scene_and_follows_the_fraction() -> None:
    ids = [f"scene-{i}" for i in range(2000)]
    splits = [scene_split(s, test_fraction=0.2) for s in ids]
    assert splits == [scene_split(s, test_fraction=0.2) for s in ids]
    assert 0.17 < splits.count("test") / len(ids) < 0.23
    assert all(scene_split(s, test_fraction=0.0) == "train" for s in ids[:50])
    assert all(scene_split(s, test_fraction=1.0) == "test" for s in ids[:50])
    other = [scene_split(s, test_fraction=0.2, split_seed=1) for s in ids]
    assert other != splits


def test_plan_uses_one_seed_per_pair_for_every_config_and_shards_partition_it() -> None:
    sources = builtin_sources(3)
    kw = dict(pairs_per_scene=4, run_seed=5, frames=8, resolution=(32, 16), test_fraction=0.5)
    full = make_plan(sources, [CFG_A, CFG_B], **kw)
    assert len(full) == 3 * 4 * 2
    for j in full:
        assert j.seed == pair_seed(5, j.source.id, j.index)
    by_pair = {(j.source.id, j.index): set() for j in full}
    for j in full:
        by_pair[(j.source.id, j.index)].add(j.seed)
    assert all(len(v) == 1 for v in by_pair.values())
    shards = [make_plan(sources, [CFG_A, CFG_B], shard_index=i, num_shards=3, **kw) for i in range(3)]
    ids = [j.pair_id for s in shards for j in s]
    assert sorted(ids) == sorted(j.pair_id for j in full)
    assert [len(s) for s in shards] == [8, 8, 8]
    with pytest.raises(ValueError, match="distinct"):
        make_plan(sources, [CFG_A, CFG_A], **kw)


def test_discover_finds_scene_files_cameras_and_reports_bad_inputs(tmp_path: Path, fixtures_dir: Path) -> None:
    single = fixtures_dir / "splatapult_test.ply"
    # folder with a scene and transforms.json
    a = tmp_path / "garden"
    a.mkdir()
    shutil.copy(single, a / "splat.ply")
    (a / "transforms.json").write_text("{}")
    # INRIA training output with a COLMAP model
    b = tmp_path / "room"
    (b / "point_cloud" / "iteration_7000").mkdir(parents=True)
    (b / "point_cloud" / "iteration_30000").mkdir(parents=True)
    shutil.copy(single, b / "point_cloud" / "iteration_7000" / "point_cloud.ply")
    shutil.copy(single, b / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    (b / "sparse" / "0").mkdir(parents=True)
    (b / "sparse" / "0" / "cameras.txt").write_text("")
    (b / "sparse" / "0" / "images.txt").write_text("")
    # ambiguous folder and a missing path
    c = tmp_path / "two"
    c.mkdir()
    shutil.copy(single, c / "x.ply")
    shutil.copy(single, c / "y.ply")
    sources, problems = discover([a, b, single, c, tmp_path / "missing.ply"])
    by_id = {s.id: s for s in sources}
    assert set(by_id) == {"garden", "room", "splatapult_test"}
    assert by_id["garden"].cameras_kind == "transforms"
    assert by_id["room"].path.endswith("iteration_30000/point_cloud.ply")
    assert by_id["room"].cameras_kind == "colmap"
    assert by_id["splatapult_test"].cameras is None
    assert {Path(p).name for p, _ in problems} == {"two", "missing.ply"}
    assert any("several scene files" in m for _, m in problems)


def test_discover_gives_clashing_names_stable_distinct_ids(tmp_path: Path, fixtures_dir: Path) -> None:
    for d in ("x", "y"):
        (tmp_path / d).mkdir()
        shutil.copy(fixtures_dir / "splatapult_test.ply", tmp_path / d / "scene.ply")
    s1, _ = discover([tmp_path / "x" / "scene.ply", tmp_path / "y" / "scene.ply"])
    s2, _ = discover([tmp_path / "y" / "scene.ply", tmp_path / "x" / "scene.ply"])
    assert len({s.id for s in s1}) == 2
    assert {s.id: s.path for s in s1} == {s.id: s.path for s in s2}


def _record(pid: str, frames: int = 2) -> dict:
    d = f"pairs/{pid}"
    return {"pair_id": pid, "frames": frames, "depth": False, "video": False,
            "paths": {"dir": d, "cameras": f"{d}/cameras.json", "clean": f"{d}/clean", "corrupted": f"{d}/corrupted"}}


def test_manifest_ignores_a_line_cut_short_and_checks_files_on_disk(tmp_path: Path) -> None:
    m = tmp_path / "manifest.jsonl"
    manifest.append(m, _record("s/a/0000"))
    with open(m, "a") as f:
        f.write(json.dumps(_record("s/a/0001"))[:40])  # a kill in the middle of a line
    recs = manifest.load(tmp_path)
    assert list(recs) == ["s/a/0000"]
    rec = recs["s/a/0000"]
    assert not manifest.is_complete(tmp_path, rec)
    for side in ("clean", "corrupted"):
        (tmp_path / rec["paths"][side]).mkdir(parents=True)
        for i in range(2):
            (tmp_path / rec["paths"][side] / f"{i:05d}.png").write_bytes(b"x")
    assert not manifest.is_complete(tmp_path, rec)  # cameras.json still missing
    (tmp_path / rec["paths"]["cameras"]).write_text("{}")
    assert manifest.is_complete(tmp_path, rec)
    # shard manifests are merged
    manifest.append(tmp_path / manifest.manifest_name(1, 4), _record("s/a/0002"))
    assert set(manifest.load(tmp_path)) == {"s/a/0000", "s/a/0002"}


def test_cli_dry_run_shows_the_plan_without_writing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ds"
    rc = main(["curate", "--out", str(out), "--dry-run", "-k", "3", "--frames", "4", "--size", "32x16",
               "--config", "blur2d", "--config", "blur2d@3"])
    assert rc == 0
    err = capsys.readouterr().err
    assert "plan: 12 pairs (12 to make, 0 done), 2 scene(s), configs blur2d, blur2d-s3" in err
    assert f"seed={pair_seed(0, 'sample-0', 2)}" in err
    assert not out.exists()


def test_cli_rejects_a_bad_config_name(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["curate", "--out", str(tmp_path), "--config", "nonsense", "--dry-run"]) == 2
    assert "expected one of" in capsys.readouterr().err


def test_inria_cameras_json_is_read_as_camera_to_world(tmp_path: Path) -> None:
    from morphgs.curation.sources import read_inria_cameras

    # camera at (0,-5,0) looking along +y, z up: c2w rotation columns right (1,0,0), down (0,0,-1), fwd (0,1,0)
    cam = {"id": 0, "img_name": "b", "width": 80, "height": 60, "position": [0, -5, 0],
           "rotation": [[1, 0, 0], [0, 0, 1], [0, -1, 0]], "fx": 100, "fy": 120}
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps([cam, {**cam, "img_name": "a", "position": [1, -5, 0]}]))
    cams = read_inria_cameras(p, resolution=None)
    np.testing.assert_allclose(cams[0].center, [1, -5, 0])  # sorted by img_name
    np.testing.assert_allclose(cams[1].project([1.0, 0.0, 0.5]), [[40 + 100 / 5, 30 - 120 * 0.5 / 5]], atol=1e-9)


def test_stale_temporaries_of_dead_processes_are_removed(tmp_path: Path) -> None:
    import socket
    import subprocess
    import sys

    from morphgs.curation.runner import _clean_stale_tmp

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    pid = int(dead.stdout)
    root = tmp_path / ".tmp"
    host = socket.gethostname()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        (root / f"{host}-{pid}-abc").mkdir(parents=True)  # a dead run
        (root / f"{host}-{os.getpid()}-def").mkdir()  # an earlier process with our pid (reused)
        (root / f"{host}-{live.pid}-def").mkdir()  # a concurrent run on this host
        (root / f"otherhost-{pid}-ghi").mkdir()  # another host's run (shared filesystem)
        _clean_stale_tmp(tmp_path)
    finally:
        live.kill()
        live.wait()
    assert sorted(p.name for p in root.iterdir()) == sorted([f"{host}-{live.pid}-def", f"otherhost-{pid}-ghi"])


def test_plain_progress_without_tqdm_reports_rate_and_eta(capsys: pytest.CaptureFixture[str]) -> None:
    from morphgs.curation.runner import _PlainProgress

    bar = _PlainProgress(4, True)
    bar.update(1)
    bar.update(1)
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("curate: 1/4 pairs, ") and "pairs/s, ETA" in err[1]
    _PlainProgress(4, False).update(1)
    assert capsys.readouterr().err == ""
