"""Popping (issue 36; docs/artifacts.md): Gaussians that vanish for a cone of viewing directions
between the virtual training views, drawn by `Strength("popping", s)` and honoured by every render.

What a user relies on: the caps' bytes are pinned and the same for 1, 2 and 8 threads; a camera
always renders the same frame (a revisited view, another chunking); the training views are the
clean frames; flips happen and grow with strength; every path that renders a corrupted scene
(render_pair, curate, calibrate's Bench, a PLY from `morphgs perturb`) pops; configs parse and a
bad one is one clear error."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import trajectory
from morphgs.pair import Corruption, iter_pair_chunks, render_pair
from morphgs.strength import POPPING_EXTRAS, Strength
from test_artifacts import room

#: sha256 (first 32 hex digits) of popping's caps and keep mask on `room()` at strength 1.5,
#: alone and in a mix with holes and floaters (the caps follow the rows the holes keep).
PINNED = "a2d1075fda9598b136de1a8b49fd8aee"


def digest() -> str:
    scene, cams = room()
    h = hashlib.sha256()
    mix = Strength("sparse-like", 1.5, {"holes": 0.1, "floaters": 0.2, "popping": 0.3})
    for cfg in (Strength("popping", 1.5), mix):
        out, mask = cfg.apply(scene, seed=20261128, return_mask=True, cameras=cams)
        for f in ("means", "opacity_logits", "sh0"):
            h.update(np.ascontiguousarray(getattr(out, f)).tobytes())
        for name in POPPING_EXTRAS:
            h.update(np.ascontiguousarray(out.extras[name]).tobytes())
        h.update(mask.tobytes())
    return h.hexdigest()[:32]


def test_the_bytes_are_pinned_and_the_same_for_1_2_and_8_threads() -> None:
    from thread_digests import digests_by_threads

    got = digests_by_threads("test_popping")
    assert got[1] == got[2] == got[8], got
    assert got[1] == PINNED, f"popping's bytes changed: {got[1]} (pinned {PINNED})"


def hidden(scene: morphgs.GaussianScene, cams: morphgs.Cameras) -> np.ndarray:
    """(F, N) which Gaussians each camera does not see: the documented rule, in float32 in the
    renderer's order of operations, h > 0 and dot(unit(mu - centre), axis) > 1 - h."""
    ex = scene.extras
    if "popping_h" not in ex:
        return np.zeros((len(cams), len(scene)), bool)
    axis = np.stack([ex[k] for k in POPPING_EXTRAS[:3]], axis=1)
    h = ex["popping_h"]
    out = []
    for cam in cams:
        d = scene.means - np.asarray(cam.center, np.float64).astype(np.float32)
        n = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        u = d / n[:, None]
        cos = u[:, 0] * axis[:, 0] + u[:, 1] * axis[:, 1] + u[:, 2] * axis[:, 2]
        out.append((h > 0) & (cos > np.float32(1) - h))
    return np.array(out)


def test_each_frame_renders_the_scene_without_what_its_camera_hides() -> None:
    scene, cams = room()
    out = Strength("popping", 2.0).apply(scene, seed=5, cameras=cams)
    frames = morphgs.render(out, cams).rgb
    mask = hidden(out, cams)
    assert mask.any(axis=1).sum() > len(cams) // 2
    for f in (1, 5, 11):
        plain = morphgs.GaussianScene.from_arrays(
            means=out.means, quats=out.quats, log_scales=out.log_scales, opacity_logits=out.opacity_logits,
            sh0=out.sh0, sh_rest=out.sh_rest).subset(~mask[f])
        assert np.array_equal(frames[f], morphgs.render(plain, cams[f]).rgb), f


def test_a_camera_renders_the_same_frame_wherever_it_is_in_the_clip() -> None:
    scene, cams = room()
    # views 5 and 13 revisited at the end (frames 25 and 26; frame 24, every 8th, is a training view)
    path = morphgs.Cameras.from_list([*cams, cams[20], cams[5], cams[13]])
    pair = render_pair(scene, path, config=Strength("popping", 2.0), seed=3)
    bad = pair.corrupted.rgb
    assert np.array_equal(bad[5], bad[25]) and np.array_equal(bad[13], bad[26])
    assert not np.array_equal(bad[5], pair.clean.rgb[5])  # and view 5 does pop
    # rendered in chunks (as curate does), the frames are the same bytes
    corruption = Corruption.make(Strength("popping", 2.0))
    corrupted = corruption.corrupt_scene(scene, 3, path)
    chunks = [c.rgb.copy() for _, _, c, _ in iter_pair_chunks(scene, corrupted, corruption, path, chunk=7)]
    assert np.array_equal(np.concatenate(chunks), bad)


def test_the_training_views_are_the_clean_frames() -> None:
    scene, cams = room()
    pair = render_pair(scene, cams, config=Strength("popping", 3.0, train_every=6), seed=9)
    same = [np.array_equal(a, b) for a, b in zip(pair.clean.rgb, pair.corrupted.rgb, strict=True)]
    assert all(same[::6]), same
    assert sum(not s for s in same) > len(cams) // 2, same


def flips(strength: float) -> int:
    scene, cams = room()
    mask = hidden(Strength("popping", strength).apply(scene, seed=2, cameras=cams), cams)
    return int((mask[1:] != mask[:-1]).sum())


def test_visibility_flips_along_the_clip_and_more_with_strength() -> None:
    counts = [flips(s) for s in (0.0, 0.5, 1.0, 2.0)]
    assert counts[0] == 0 and 0 < counts[1] < counts[2] < counts[3], counts


def test_strength_zero_is_the_identity() -> None:
    scene, cams = room()
    out = Strength("popping", 0.0).apply(scene, seed=1, cameras=cams)
    assert not set(POPPING_EXTRAS) & set(out.extras)
    assert np.array_equal(morphgs.render(out, cams).rgb, morphgs.render(scene, cams).rgb)


def test_calibration_and_a_perturbed_ply_pop_too(tmp_path: Path) -> None:
    from morphgs.calibration.pairs import Bench, RealPair

    scene, cams = room()
    cfg = Strength("popping", 2.0)
    pair = render_pair(scene, cams, config=cfg, seed=4)
    frames = np.zeros((len(cams), cams.height, cams.width, 3), np.float32)
    bench = Bench({"room": scene}, [RealPair("p", "room", "r", 4, cams, frames, frames)])
    want = np.rint(np.clip(pair.corrupted.rgb, 0, 1) * np.float32(255)) / np.float32(255)
    assert np.array_equal(bench.corrupted(cfg, 0), want)
    # `morphgs perturb` writes the caps into the PLY; rendering the file pops the same way
    src, dst = tmp_path / "room.ply", tmp_path / "popped.ply"
    morphgs.save_ply(scene, src)
    r = subprocess.run([sys.executable, "-m", "morphgs", "perturb", str(src), str(dst), "--preset", "popping~2",
                        "--seed", "4", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["popping"] > 0
    loaded = morphgs.load(dst)
    orbit = trajectory.for_scene(scene, 64, resolution=(256, 192))  # perturb's training views: every 8th
    want = cfg.apply(morphgs.load(src), seed=4, cameras=orbit)
    for name in POPPING_EXTRAS:
        assert np.array_equal(loaded.extras[name], want.extras[name]), name
    mask = hidden(loaded, orbit)
    assert mask.any() and not mask[::8].any()
    assert not np.array_equal(morphgs.render(loaded, orbit[1:8]).rgb, morphgs.render(scene, orbit[1:8]).rgb)


def test_a_popping_config_parses_and_runs_through_curate(tmp_path: Path) -> None:
    cfg = {"kind": "strength", "family": "popping", "strength": 2.0, "train_every": 4, "ops": {"popping": 0.4}}
    st = Strength.from_dict(cfg)
    assert st.to_dict() == cfg and st.values() == {"popping": pytest.approx(1 - 0.6**2)}
    (tmp_path / "pop.json").write_text(json.dumps(cfg), encoding="utf-8")
    out = tmp_path / "data"
    r = subprocess.run([sys.executable, "-m", "morphgs", "curate", "--out", str(out), "--config",
                        str(tmp_path / "pop.json"), "--sample-gaussians", "3000", "--pairs-per-scene", "1",
                        "--frames", "12", "--size", "64x48", "--test-fraction", "0"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    recs = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert recs and all(r["config"]["name"] == "pop" for r in recs)
    for rec in recs:
        clean = morphgs.media.read_clip(out / rec["paths"]["clean"])
        bad = morphgs.media.read_clip(out / rec["paths"]["corrupted"])
        same = [np.array_equal(a, b) for a, b in zip(clean, bad, strict=True)]
        assert all(same[::4]) and not all(same), same


def test_a_bad_popping_field_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"ops.popping must be a fraction in \[0, 1\)"):
        Strength("popping", 1.0, {"popping": 1.0})
    with pytest.raises(ValueError, match=r"the sparse-view op\(s\) popping need the pair's cameras"):
        Strength("popping", 1.0).apply(room()[0], seed=0)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "strength", "family": "popping", "ops": {"popping": 0.3, "popping_rate": 2}}))
    r = subprocess.run([sys.executable, "-m", "morphgs", "curate", "--out", str(tmp_path / "o"), "--config", str(bad),
                        "--sample-gaussians", "2000"], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and r.stderr.count("\n") == 1, r.stderr
    assert str(bad) in r.stderr and "popping_rate" in r.stderr, r.stderr
    scene = room()[0]
    half = morphgs.GaussianScene.from_arrays(
        means=scene.means, quats=scene.quats, log_scales=scene.log_scales, opacity_logits=scene.opacity_logits,
        sh0=scene.sh0, extras={"popping_h": np.zeros(len(scene), np.float32)})
    with pytest.raises(ValueError, match="without popping_x, popping_y, popping_z"):
        morphgs.render(half, room()[1][0])
