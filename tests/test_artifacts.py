"""The sparse-view corruption families (issue 36; docs/artifacts.md): depth, view_color, needles,
holes, dilate, floaters and `sparse-like`, as `FAMILY~S` strength configs.

What a user relies on: the bytes are pinned and the same for 1, 2 and 8 threads; the training
views (every K-th camera of the pair's path) stay closer to clean than the views between them,
as a real sparse fit's do; holes are spatially coherent; the configs compose in JSON and through
curate; bad configs and missing cameras are one clear error."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import morphgs
from morphgs import synthetic, trajectory
from morphgs.strength import ARTIFACT_OPS, FAMILIES, Strength

FAMS = (*ARTIFACT_OPS, "shatter", "sparse-like")  # popping: tests/test_popping.py

#: sha256 (first 32 hex digits) of every sparse-view family's output on `room()` at strength 1.5 (the
#: six Rust ops' part unchanged since they were pinned at cdcbd816...; shatter re-pinned when it moved to Rust,
#: and again when a fragment whose footprint reaches another training view from outside its image was dropped).
PINNED = "99b5c4e9905437d1870b56a9c65ffe53"


def room(views: int = 24) -> tuple[morphgs.GaussianScene, morphgs.Cameras]:
    """A built-in room (SH degree 3) and a `views`-view 330-degree orbit inside it at 96x72 (the
    pinned scene of this file, test_popping's and test_haze's)."""
    scene = synthetic.scene(6000, sh_degree=3, seed=4)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], views, start_degrees=0.0, arc_degrees=330,
                            fov_y_degrees=50.0, resolution=(96, 72))
    return scene, cams


def digest() -> str:
    scene, cams = room()
    h = hashlib.sha256()
    for fam in FAMS:
        out, mask = Strength(fam, 1.5).apply(scene, seed=20261128, return_mask=True, cameras=cams)
        for f in ("means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest"):
            h.update(np.ascontiguousarray(getattr(out, f)).tobytes())
        h.update(mask.tobytes())
    return h.hexdigest()[:32]


def test_the_bytes_are_pinned_and_the_same_for_1_2_and_8_threads() -> None:
    from thread_digests import digests_by_threads

    got = digests_by_threads("test_artifacts")
    assert got[1] == got[2] == got[8], got
    assert got[1] == PINNED, f"the sparse-view ops' bytes changed: {got[1]} (pinned {PINNED})"


def _psnr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    err = ((a.astype(np.float64) - b) ** 2).mean(axis=(1, 2, 3))
    return 10 * np.log10(255.0**2 / np.maximum(err, 1e-12))


@pytest.mark.parametrize("family", ["depth", "view_color", "needles", "shatter"])
def test_the_training_views_stay_closer_to_clean_than_the_views_between_them(family: str) -> None:
    scene, cams = room()
    st = Strength(family, 1.0, train_every=6)
    clean = morphgs.render(scene, cams).to_uint8()
    bad = morphgs.render(st.apply(scene, seed=1, cameras=cams), cams).to_uint8()
    p = _psnr(bad, clean)
    train, other = p[::6], np.delete(p, np.arange(0, len(p), 6))
    assert train.mean() > other.mean() + 1.0, (train, other)
    assert np.isfinite(other).all() and other.mean() < 45  # and the views between them do change


def test_shatter_replaces_a_superset_by_fragments_that_rebuild_the_training_views() -> None:
    """shatter (docs/artifacts.md): a larger strength removes a superset of the Gaussians and
    spawns more fragments; the fragments carry view-dependent colour (band-1 SH, the scene
    promoted from degree 0) and lie on their training rays at wrong depths, more spread at a
    larger value."""
    scene, cams = room()
    n = len(scene)
    lo_scene, lo = Strength("shatter", 0.5, train_every=6).apply(scene, seed=2, return_mask=True, cameras=cams)
    hi_scene, hi = Strength("shatter", 2.0, train_every=6).apply(scene, seed=2, return_mask=True, cameras=cams)
    assert (~lo[:n]).sum() > 0 and np.all(hi[:n] <= lo[:n])
    # the mask: a row per input Gaussian, then one per fragment (all kept)
    assert len(hi) - n > len(lo) - n > 0 and lo[n:].all() and hi[n:].all()
    assert len(hi_scene) == hi.sum() and len(lo_scene) == lo.sum()
    flat = synthetic.scene(6000, sh_degree=0, seed=4)
    out = Strength("shatter", 1.0, train_every=6).apply(flat, seed=2, cameras=cams)
    assert out.sh_degree == 1 and np.abs(np.asarray(out.sh_rest)).max() > 0
    # the fragments sit on their training rays at wrong depths, spread wider at a larger value
    from morphgs import shatter

    train = cams[::6]
    r = morphgs.render(scene, train)
    t_n, h, w = len(train), train.height, train.width
    img, dep = np.asarray(r.rgb).reshape(t_n, h, w, 3), np.asarray(r.depth).reshape(t_n, h, w)
    alpha = np.asarray(r.alpha).reshape(t_n, h, w)

    def spread(value: float) -> float:
        f = shatter.fragments(value, img, dep, alpha, train.world_to_camera, train.K, n, seed=2)
        ratios = []
        for t in range(t_n):
            m = train.world_to_camera[t]
            c = f["means"][f["view"] == t].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
            u = np.clip((train.K[t][0, 0] * c[:, 0] / c[:, 2] + train.K[t][0, 2]).astype(int), 0, w - 1)
            v = np.clip((train.K[t][1, 1] * c[:, 1] / c[:, 2] + train.K[t][1, 2]).astype(int), 0, h - 1)
            ratios.append(np.log(c[:, 2] / dep[t][v, u]))
        q = np.percentile(np.concatenate(ratios), [25, 75])
        return float(q[1] - q[0])

    assert 0.0 < spread(1.0) < spread(3.0)


def test_holes_are_spatially_coherent_and_grow_as_supersets() -> None:
    scene, _ = room()
    lo = Strength("holes", 1.0).apply(scene, seed=3, return_mask=True)[1]
    hi = Strength("holes", 3.0).apply(scene, seed=3, return_mask=True)[1]
    assert (~lo).sum() > 0 and np.all(hi <= lo)  # a larger strength empties a superset of the cells
    # the removed Gaussians cluster: their nearest neighbour is removed far more often than chance
    means = np.asarray(scene.means)
    d = ((means[:, None, :] - means[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d, np.inf)
    nn = d.argmin(1)
    removed = ~lo
    assert (removed[nn][removed]).mean() > 3 * removed.mean()


def test_families_compose_in_json_and_through_curate(tmp_path: Path) -> None:
    cfg = {"kind": "strength", "family": "sparse-like", "strength": 0.8, "train_every": 4,
           "ops": {"depth": 0.4, "needles": 0.3, "floaters": 0.5}}
    (tmp_path / "mine.json").write_text(json.dumps(cfg), encoding="utf-8")
    st = Strength.from_dict(cfg)
    assert st.to_dict() == {"kind": "strength", "family": "sparse-like", "strength": 0.8, "train_every": 4,
                            "ops": {"depth": 0.4, "needles": 0.3, "floaters": 0.5}}
    out = tmp_path / "data"
    r = subprocess.run([sys.executable, "-m", "morphgs", "curate", "--out", str(out), "--config",
                        str(tmp_path / "mine.json"), "--config", "needles~2",
                        "--sample-gaussians", "3000", "--pairs-per-scene", "1", "--frames", "8", "--size", "64x48",
                        "--test-fraction", "0"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    recs = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    names = [r["config"]["name"] for r in recs]
    assert set(names) == {"mine", "needles-s2"} and names.count("mine") == names.count("needles-s2") >= 1
    for rec in recs:
        clean = morphgs.media.read_clip(out / rec["paths"]["clean"])
        bad = morphgs.media.read_clip(out / rec["paths"]["corrupted"])
        assert clean.shape == bad.shape == (8, 48, 64, 3) and not np.array_equal(clean, bad)


def test_bad_configs_and_missing_cameras_are_one_clear_error(tmp_path: Path) -> None:
    scene, _ = room()
    with pytest.raises(ValueError, match=r"need the pair's cameras"):
        Strength("depth", 1.0).apply(scene, seed=0)
    Strength("holes", 1.0).apply(scene, seed=0)  # holes and dilate need none
    with pytest.raises(ValueError, match=r"unknown strength op\(s\) 'needle'"):
        Strength("sparse-like", 1.0, {"needle": 0.2})
    with pytest.raises(ValueError, match=r"ops.holes must be a fraction in \[0, 1\)"):
        Strength("holes", 1.0, {"holes": 1.0})
    with pytest.raises(ValueError, match=r"train_every must be an integer >= 1"):
        Strength("depth", 1.0, train_every=0)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "strength", "family": "sparse-like", "ops": {"floaters": -1}}))
    r = subprocess.run([sys.executable, "-m", "morphgs", "curate", "--out", str(tmp_path / "o"), "--config", str(bad),
                        "--sample-gaussians", "2000"], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and r.stderr.count("\n") == 1
    assert str(bad) in r.stderr and "ops.floaters" in r.stderr, r.stderr


def test_the_paper_families_are_unchanged() -> None:
    assert FAMILIES["naive"] == ("position", "color", "opacity", "keep", "log_scale", "rotation")
    assert Strength("morphological", 2.0).to_dict() == {"kind": "strength", "family": "morphological",
                                                          "strength": 2.0,
                                                          "ops": {"keep": 0.5, "log_scale": 0.5, "rotation": 0.5}}


def test_shatter_kernel_names_maps_that_do_not_match_its_cameras() -> None:
    """`morphgs.shatter.fragments` (the Rust kernel): maps of the wrong shape, a camera count
    that differs from the views', or a bad value are one ValueError naming the problem."""
    from morphgs import shatter

    scene, cams = room()
    train = cams[::6]
    r = morphgs.render(scene, train)
    t_n, h, w = len(train), train.height, train.width
    img, dep = np.asarray(r.rgb).reshape(t_n, h, w, 3), np.asarray(r.depth).reshape(t_n, h, w)
    alpha = np.asarray(r.alpha).reshape(t_n, h, w)
    with pytest.raises(ValueError, match="depth and alpha"):
        shatter.fragments(1.0, img, dep[:, :-1], alpha, train.world_to_camera, train.K, 10, seed=0)
    with pytest.raises(ValueError, match="one camera per training view"):
        shatter.fragments(1.0, img, dep, alpha, train.world_to_camera[:-1], train.K[:-1], 10, seed=0)
    with pytest.raises(ValueError, match="shatter value"):
        shatter.fragments(float("nan"), img, dep, alpha, train.world_to_camera, train.K, 10, seed=0)
    with pytest.raises(ValueError, match="max_error"):
        shatter.fragments(1.0, img, dep, alpha, train.world_to_camera, train.K, 10, seed=0, max_error=-1.0)
    # value 0 makes nothing; the removal is a superset at a larger value
    assert len(shatter.fragments(0.0, img, dep, alpha, train.world_to_camera, train.K, 10, seed=0)["means"]) == 0
    lo, hi = shatter.removal(5000, 0.5, 1), shatter.removal(5000, 2.0, 1)
    assert lo.dtype == bool and np.all(hi[lo]) and hi.sum() > lo.sum() > 0
