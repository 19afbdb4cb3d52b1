"""E_flow, the warping error and geometric flow: known motions, known flicker, exact camera flow."""

from __future__ import annotations

import numpy as np
import pytest

import morphgs
from morphgs import metrics, synthetic, trajectory
from morphgs.camera import Camera, Cameras
from morphgs.metrics import MetricError

DX, DY = 2, 1  # content motion per frame of the translating clip, pixels


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.random((h, w, 3)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3 - 1, 0.05, 0.95)


def _translating_clip(frames: int = 4, h: int = 72, w: int = 96) -> np.ndarray:
    """Frames cut from a larger texture so that content moves by (+DX, +DY) pixels per frame."""
    big = _texture(h + 40, w + 40)
    return np.stack([big[20 - t * DY: 20 - t * DY + h, 20 - t * DX: 20 - t * DX + w] for t in range(frames)])


def test_dis_flow_finds_a_known_translation() -> None:
    clip = _translating_clip()
    flow = metrics.optical_flow(clip)
    assert flow.shape == (3, 72, 96, 2) and flow.dtype == np.float32
    inner = flow[:, 8:-8, 8:-8]
    np.testing.assert_allclose(np.median(inner, axis=(0, 1, 2)), [DX, DY], atol=0.05)
    back = metrics.optical_flow(clip, backward=True)
    np.testing.assert_allclose(np.median(back[:, 8:-8, 8:-8], axis=(0, 1, 2)), [-DX, -DY], atol=0.05)


def test_e_flow_is_zero_for_the_ground_truth_and_the_missing_motion_for_a_frozen_video() -> None:
    clip = _translating_clip()
    assert metrics.flow_epe(clip, clip) == 0.0
    frozen = np.repeat(clip[:1], len(clip), axis=0)
    per_pair = metrics.flow_epe(frozen, clip, reduction="none")
    assert per_pair.shape == (3,)
    np.testing.assert_allclose(per_pair, np.hypot(DX, DY), rtol=0.08)
    exact = np.broadcast_to(np.array([DX, DY], np.float32), (3, 72, 96, 2))
    assert metrics.flow_epe(clip, clip, target_flow=exact) < 0.15   # DIS against the true motion


def test_warping_error_measures_flicker_along_the_motion() -> None:
    clip = _translating_clip()
    exact = np.broadcast_to(np.array([DX, DY], np.float32), (3, 72, 96, 2))
    assert metrics.warping_error(clip, flow=exact) == pytest.approx(0.0, abs=1e-12)
    flicker = clip + np.array([0.0, 0.05, 0.0, 0.05])[:, None, None, None]  # stays inside [0, 1]
    np.testing.assert_allclose(metrics.warping_error(flicker, flow=exact, reduction="none"), 0.05**2, rtol=1e-6)
    # the reference flow and its occlusions from DIS on the ground truth
    steady = metrics.warping_error(clip, clip)
    assert steady < 2e-4
    assert metrics.warping_error(flicker, clip) == pytest.approx(0.05**2 + steady, rel=0.1)


def test_one_pass_gives_both_errors_as_the_separate_functions() -> None:
    clip = _translating_clip()
    flicker = np.clip(clip + np.array([0.0, 0.05, 0.0, 0.05])[:, None, None, None], 0, 1)
    both = metrics.temporal_errors(flicker, clip)
    np.testing.assert_array_equal(both["eflow"], metrics.flow_epe(flicker, clip, reduction="none"))
    np.testing.assert_array_equal(both["ewarp"], metrics.warping_error(flicker, clip, reduction="none"))


def test_occlusion_mask_flags_forward_backward_disagreement() -> None:
    fw = np.zeros((20, 30, 2), np.float32)
    fw[...] = (3.0, 0.0)
    bw = np.zeros_like(fw)
    bw[...] = (-3.0, 0.0)
    assert not metrics.occlusion_mask(fw, bw)[2:-2, 2:-5].any()    # consistent motion: nothing occluded
    bw[:, 15:] = (0.0, 0.0)                                        # where frame t+1 disagrees
    occ = metrics.occlusion_mask(fw, bw)
    assert occ[:, 13:25].all() and not occ[:, :10].any()


def test_geometric_flow_of_a_sideways_camera_over_a_plane() -> None:
    fx, z, b = 50.0, 4.0, 0.2
    c0 = Camera.from_c2w(np.eye(4), fx=fx, width=32, height=24)
    moved = np.eye(4)
    moved[0, 3] = b
    c1 = Camera.from_c2w(moved, fx=fx, width=32, height=24)
    flow, valid = metrics.geometric_flow(np.full((24, 32), z), c0, c1)
    np.testing.assert_allclose(flow[valid][:, 0], -fx * b / z, rtol=1e-6)
    np.testing.assert_allclose(flow[valid][:, 1], 0.0, atol=1e-6)
    assert valid[:, 3:].all() and not valid[:, :2].any()            # the camera moves right: the left edge leaves
    near = np.full((24, 32), z)
    near[:, :10] = 1.0                                             # something closer hides them in frame t+1
    _, seen = metrics.geometric_flow(np.full((24, 32), z), c0, c1, depth_to=near)
    assert not seen[:, :12].any() and seen[:, 12:].all()           # columns landing on u < 10 are hidden
    _, holes = metrics.geometric_flow(np.zeros((24, 32)), c0, c1)
    assert not holes.any()


def test_geometric_flow_of_a_render_agrees_with_dis() -> None:
    scene = synthetic.scene(n_gaussians=30000, sh_degree=0, seed=0)
    o = synthetic.suggested_orbit()
    cams = trajectory.orbit(o.center, o.radius, o.height - o.center[2], 3, start_degrees=150, arc_degrees=2,
                            resolution=(160, 112))
    r = morphgs.render(scene, cams)
    flows, valid = metrics.geometric_flows(r.depth, cams)
    good = valid & (r.alpha[:-1] > 0.99)
    assert good.mean() > 0.3
    dis = metrics.optical_flow(np.clip(r.rgb, 0, 1))
    assert np.median(np.linalg.norm(dis - flows, axis=-1)[good]) < 0.3
    e = metrics.flow_epe(np.clip(r.rgb, 0, 1), np.clip(r.rgb, 0, 1), target_flow=flows, valid=good)
    assert 0 < e < 0.5


def test_flow_bad_input() -> None:
    clip = _translating_clip()
    with pytest.raises(MetricError, match="at least 2 frames"):
        metrics.optical_flow(clip[:1])
    with pytest.raises(MetricError, match="shapes differ"):
        metrics.flow_epe(clip, clip[:3])
    with pytest.raises(MetricError, match="reference flow must be"):
        metrics.flow_epe(clip, clip, target_flow=np.zeros((2, 72, 96, 2)))
    with pytest.raises(MetricError, match="preset"):
        metrics.optical_flow(clip, preset="slow")
    with pytest.raises(MetricError, match="ground-truth clip or reference flows"):
        metrics.warping_error(clip)
    cams = Cameras.from_list([Camera.from_c2w(np.eye(4), fx=10, width=8, height=6)] * 2)
    with pytest.raises(MetricError, match="3 cameras for 2"):
        metrics.geometric_flows(np.ones((2, 6, 8)), list(cams) + [cams[0]])
    with pytest.raises(MetricError, match="does not match a 8x6 camera"):
        metrics.geometric_flow(np.ones((5, 8)), cams[0], cams[1])


def test_flow_errors_and_ssim_do_not_depend_on_opencv_threads() -> None:
    import cv2

    clip = _translating_clip()
    flicker = np.clip(clip + np.array([0.0, 0.05, 0.0, 0.05])[:, None, None, None], 0, 1).astype(np.float32)
    before = cv2.getNumThreads()
    try:
        results = []
        for n in (1, 2):
            cv2.setNumThreads(n)
            errs = metrics.temporal_errors(flicker, clip)
            results.append((errs["eflow"], errs["ewarp"], metrics.ssim(flicker, clip, reduction="none")))
    finally:
        cv2.setNumThreads(before)
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)
