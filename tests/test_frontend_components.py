"""Frontend components: DIS correspondences on synthetic warps, keyframe policy, frame graph updates, frame
records."""
import cv2
import numpy as np
import pytest
import torch

from vigs_core.frontend import (DISFlowConfig, DISFlowEstimator, FrameGraph, FrameGraphConfig, KeyframePolicy,
                                KeyframePolicyConfig, PixelGrid)
from vigs_core.frontend.odometry import DenseOdometry, Keyframe, PoseRows, _Frame
from vigs_core.solver import Intrinsics

cv2.setNumThreads(1)
W, H = 192, 128


def texture(seed=0, w=W, h=H):
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.5, 1.0), (4.0, 1.5), (12.0, 2.0)):
        b = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        img += amp * b / b.std()
    return np.clip(128 + 18 * img, 0, 255).astype(np.uint8)


def warp(img, A):
    """Target image under the affine map x' = A [x, y, 1] (A (2, 3)) of the source."""
    return cv2.warpAffine(img, A, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)


def test_grid_coords_are_cell_centres():
    g = PixelGrid(40, 24, 8)
    c = g.coords()
    assert (g.rows, g.cols, g.size) == (3, 5, 15)
    assert np.allclose(c[0], [3.5, 3.5]) and np.allclose(c[-1], [35.5, 19.5])
    cell, inside = g.cell_of(np.array([[3.5, 3.5], [39.9, 23.9], [40.0, 1.0]]))
    assert list(cell[:2]) == [0, 14] and list(inside) == [True, True, False]
    with pytest.raises(ValueError):
        PixelGrid(4, 4, 8)


@pytest.mark.parametrize("A", [np.float32([[1, 0, 3.3], [0, 1, -2.1]]),
                               np.float32([[1.02, 0.01, -1.5], [-0.01, 1.02, 2.0]])])
def test_dis_recovers_affine_warp(A):
    src = texture()
    dst = warp(src, A)
    est = DISFlowEstimator(PixelGrid(W, H, 8), DISFlowConfig(preset="medium", finest_scale=0))
    corr = est.estimate(src, dst)
    c = est.grid.coords()
    truth = c @ A[:, :2].T.astype(np.float64) + A[:, 2]
    err = np.linalg.norm(corr.target - truth, axis=1)
    good = corr.weight > 0.5
    assert good.mean() > 0.7
    assert np.median(err[good]) < 0.15
    assert corr.mean_flow == pytest.approx(np.linalg.norm(truth - c, axis=1).mean(), abs=0.5)


def test_flow_without_an_initial_flow_does_not_depend_on_the_previous_call():
    """Without an initial flow DIS starts from zero, not from the initial flow of the call before it (OpenCV 5.0's
    DIS reuses that one unless a zero flow is passed)."""
    est = DISFlowEstimator(PixelGrid(W, H, 8))
    src = texture(2)
    dst = warp(src, np.float32([[1, 0, 12.0], [0, 1, -6.0]]))
    fresh = est.dense_flow(src, dst, None)
    other = texture(3)
    est.dense_flow(other, warp(other, np.float32([[1, 0, -30.0], [0, 1, 20.0]])),
                   np.tile(np.float32([-30.0, 20.0]), (H, W, 1)))
    assert np.array_equal(est.dense_flow(src, dst, None), fresh)


def test_initial_flow_helps_large_motion_and_confidence_flags_occlusion():
    src = texture(1)
    A = np.float32([[1, 0, 40.0], [0, 1, 0.0]])
    dst = warp(src, A)
    # paste an unrelated patch: the correspondences that land there must lose confidence
    dst[40:88, 100:150] = texture(7)[40:88, 100:150]
    est = DISFlowEstimator(PixelGrid(W, H, 8), DISFlowConfig(preset="ultrafast"))
    c = est.grid.coords()
    truth = c + [40.0, 0.0]
    guided = est.estimate(src, dst, initial_target=truth + 1.5)
    unguided = est.estimate(src, dst)
    inside = (truth[:, 0] < W - 8)
    err = lambda c: np.median(np.linalg.norm(c.target - truth, axis=1)[inside])
    assert err(guided) < 0.1 * err(unguided)  # the warp initialisation carries DIS past its search range
    occl = inside & (truth[:, 0] > 104) & (truth[:, 0] < 146) & (truth[:, 1] > 44) & (truth[:, 1] < 84)
    clean = inside & ~occl & (guided.weight > 0.5)
    assert np.median(np.linalg.norm(guided.target - truth, axis=1)[clean]) < 0.5
    assert guided.weight[occl].mean() < 0.3 * guided.weight[inside & ~occl].mean()
    # targets beyond the image border have zero confidence
    assert np.all(guided.weight[truth[:, 0] > W - 1] == 0)


def test_pair_estimate_uses_each_direction_as_the_others_backward_flow():
    src = texture(2)
    A = np.float32([[1, 0, 6.0], [0, 1, -3.0]])
    dst = warp(src, A)
    dst[40:88, 100:150] = texture(8)[40:88, 100:150]       # seen in dst only: occludes part of src
    est = DISFlowEstimator(PixelGrid(W, H, 8), DISFlowConfig(preset="ultrafast", finest_scale=0))
    c = est.grid.coords()
    fwd_truth, bwd_truth = c + [6.0, -3.0], c - [6.0, -3.0]
    ab, ba = est.estimate_pair(src, dst, fwd_truth + 1.0, bwd_truth - 1.0)
    single = est.estimate(src, dst, fwd_truth + 1.0)
    ok = (fwd_truth[:, 0] < W - 10) & (fwd_truth[:, 1] > 10) & ~((fwd_truth[:, 0] > 96) & (fwd_truth[:, 0] < 154)
                                                               & (fwd_truth[:, 1] > 36) & (fwd_truth[:, 1] < 92))
    assert np.median(np.linalg.norm(ab.target - fwd_truth, axis=1)[ok]) < 0.2
    assert np.median(np.linalg.norm(ba.target - bwd_truth, axis=1)[ok & (c[:, 0] > 10)]) < 0.2
    # same confidences as two separate estimates up to DIS noise: high on the clean part, low on the occlusion
    occl = (fwd_truth[:, 0] > 104) & (fwd_truth[:, 0] < 146) & (fwd_truth[:, 1] > 44) & (fwd_truth[:, 1] < 84)
    for corr in (ab, single):
        assert corr.weight[ok].mean() > 0.6 and corr.weight[occl].mean() < 0.3 * corr.weight[ok].mean()
    # the forward-backward term of a -> b is the flow b -> a at the targets: zero where the two agree
    fb = est.dense_flow(dst, src, est._initial_flow(bwd_truth - 1.0))
    assert np.allclose(ab.weight, est._correspondences(src, dst, est.dense_flow(src, dst, est._initial_flow(
        fwd_truth + 1.0)), fb).weight, atol=1e-6)


def test_keyframe_policy():
    p = KeyframePolicy(KeyframePolicyConfig(flow_threshold_px=2.4, max_interval_s=3.0, translation_flow_px=None))
    assert not p.is_keyframe(2.0, 0.5)
    assert p.is_keyframe(2.5, 0.5)
    assert p.is_keyframe(0.0, 3.0)
    # with the translation test: rotation-only flow makes no keyframe until the total flow is large
    q = KeyframePolicy(KeyframePolicyConfig(translation_flow_px=8.0, max_flow_px=48.0, max_interval_s=3.0))
    assert not q.is_keyframe(30.0, 0.5, translation_flow_px=1.0)
    assert q.is_keyframe(30.0, 0.5, translation_flow_px=9.0)
    assert q.is_keyframe(50.0, 0.5, translation_flow_px=0.0)
    assert q.is_keyframe(0.0, 3.0, translation_flow_px=0.0)
    assert q.is_keyframe(17.0, 0.5) and not q.is_keyframe(15.0, 0.5)  # no translation flow: total flow


def test_frame_graph_edges_and_sliding_window():
    g = FrameGraph(FrameGraphConfig(window=4, fixed=2, temporal_radius=1, covis_max_flow_px=30.0,
                                    covis_max_edges=1))
    flows = {(0, 2): 10.0, (0, 3): 25.0, (1, 3): 40.0, (0, 4): 5.0, (2, 4): 20.0}
    pf = lambda i, j: flows.get((i, j), 99.0)
    assert g.add_keyframe(0, pf) == ([], [])
    assert g.fixed_ids() == [0]
    new, removed = g.add_keyframe(1, pf)
    assert set(new) == {(0, 1), (1, 0)} and removed == []
    new, _ = g.add_keyframe(2, pf)
    assert set(new) == {(1, 2), (2, 1), (0, 2), (2, 0)}       # temporal + co-visible (flow 10 < 30)
    new, _ = g.add_keyframe(3, pf)
    assert set(new) == {(2, 3), (3, 2), (0, 3), (3, 0)}       # (1, 3) flow 40 is not co-visible
    assert g.fixed_ids() == [0, 1]
    assert g.is_temporal(2, 3) and g.is_temporal(3, 2) and not g.is_temporal(0, 3)
    new, removed = g.add_keyframe(4, pf)
    assert removed == [0] and g.keyframes == [1, 2, 3, 4]
    assert set(new) == {(3, 4), (4, 3), (2, 4), (4, 2)}       # 0 (flow 5) leaves the window: 2 is the partner
    assert all(0 not in e for e in g.edges)
    assert (3, 4) in g.edges and (4, 3) in g.edges
    with pytest.raises(ValueError):
        g.add_keyframe(2, pf)


def _window_problem(hold: bool):
    """A 4-keyframe window with exact correspondences between all pairs, keyframe 0 at its true pose and
    depth, the others perturbed; returns the odometry after window BA and the true poses and disparities."""
    import torch

    from vigs_core.frontend import Correspondences, DenseOdometry, OdometryConfig
    from vigs_core.frontend.odometry import Keyframe
    from vigs_core.geometry import se3_exp
    from vigs_core.solver import Intrinsics, reproject

    intr = Intrinsics(180.0, 180.0, (W - 1) / 2, (H - 1) / 2)
    cfg = OdometryConfig(graph=FrameGraphConfig(window=4, fixed=1, temporal_radius=3), hold_fixed_disparity=hold)
    odo = DenseOdometry(intr, W, H, cfg)
    g = torch.Generator().manual_seed(3)
    P = odo.coords.shape[0]
    poses = torch.stack([se3_exp(torch.tensor([0.1 * k, 0.02 * k, 0.01 * k, 0.01 * k, -0.02 * k, 0.0],
                                              dtype=torch.float64)) for k in range(4)])
    disps = 1.0 / (2.0 + 1.5 * torch.rand(4, P, generator=g, dtype=torch.float64))
    image = np.zeros((H, W), np.uint8)
    for k in range(4):
        xi = 0.01 * torch.randn(6, generator=g, dtype=torch.float64) * (k > 0)
        d = disps[k] * (1.0 + 0.05 * torch.randn(P, generator=g, dtype=torch.float64) * (k > 0))
        odo.keyframes[k] = Keyframe(k, k, image, se3_exp(xi) @ poses[k], d)
        new, _ = odo.graph.add_keyframe(k, lambda i, j: float("inf"))
        for i, j in new:
            proj = reproject(poses[i:i + 1], poses[j:j + 1], disps[i:i + 1], odo.coords, intr)
            odo.edges[(i, j)] = Correspondences(proj.uv[0].numpy(), proj.valid[0].numpy().astype(np.float32), 0.0)
    odo._ba(40)
    return odo, poses, disps


def test_window_ba_holds_the_fixed_keyframe_depth_as_scale_gauge():
    import torch

    odo, poses, disps = _window_problem(hold=True)
    assert torch.equal(odo.keyframes[0].disp, disps[0])
    for k in range(4):   # fixed pose + fixed depth: the monocular scale is pinned, the solution is unique
        assert (odo.keyframes[k].pose - poses[k]).abs().max() < 1e-6
        assert (odo.keyframes[k].disp - disps[k]).abs().max() < 1e-6
    free, _, _ = _window_problem(hold=False)   # only the pose fixed: the depth of keyframe 0 moves too
    assert not torch.equal(free.keyframes[0].disp, disps[0])


def test_frame_records_keep_their_poses_compactly_and_hand_out_copies():
    """Frames store ``rel`` and ``odom`` in shared chunked rows (a long run keeps every frame): across chunk
    boundaries each reads back exactly what was set, unset is None, and editing a pose read does not edit it."""
    rows = PoseRows(chunk=3)
    poses = [torch.eye(4, dtype=torch.float64) + 0.01 * k for k in range(7)]
    frames = [_Frame(k, rows, ref=0, rel=poses[k], odom=poses[k] if k % 2 else None) for k in range(7)]
    for k, f in enumerate(frames):
        assert torch.equal(f.rel, poses[k]) and f.rel.dtype == torch.float64
        assert (f.odom is None) == (k % 2 == 0)
    frames[4].rel[0, 3] = 5.0
    assert torch.equal(frames[4].rel, poses[4])
    frames[4].rel, frames[4].odom = None, poses[0]
    assert frames[4].rel is None and torch.equal(frames[4].odom, poses[0]) and torch.equal(frames[5].rel, poses[5])


def test_scaling_relative_translations_writes_the_frames_rows_across_chunks():
    """A depth rescaling of reference keyframes (a loop correction, the IMU alignment) scales the translation of
    each pose kept relative to them -- frames' ``rel`` across chunk boundaries, keyframes' ``tracked`` -- in one
    scatter per chunk: rotations, the causal poses, frames of other keyframes and unset poses stay as they were."""
    odo = DenseOdometry(Intrinsics(50.0, 50.0, 31.5, 23.5), 64, 48)
    odo._pose_rows = rows = PoseRows(chunk=3)
    R = torch.tensor(cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0], dtype=torch.float64)

    def pose(x: float) -> torch.Tensor:
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3], T[:3, 3] = R, torch.tensor([x, 2 * x, -x], dtype=torch.float64)
        return T

    odo.frames += [_Frame(k, rows, ref=k % 3, rel=None if k == 4 else pose(0.1 * k), odom=pose(k)) for k in range(8)]
    odo.keyframes[2] = Keyframe(2, 0, None, pose(0.0), None, tracked=(1, pose(0.5)))
    old_tracked = odo.keyframes[2].tracked[1]
    odo.scale_relative_translations({1: 2.0, 2: 0.5})
    for k, f in enumerate(odo.frames):
        factor = {0: 1.0, 1: 2.0, 2: 0.5}[k % 3]
        if k == 4:
            assert f.rel is None
            continue
        np.testing.assert_allclose(f.rel[:3, 3].numpy(), factor * pose(0.1 * k)[:3, 3].numpy(), atol=1e-15)
        assert torch.equal(f.rel[:3, :3], R) and torch.equal(f.odom, pose(k))
    np.testing.assert_allclose(odo.keyframes[2].tracked[1][:3, 3].numpy(), 2.0 * pose(0.5)[:3, 3].numpy())
    assert torch.equal(old_tracked, pose(0.5))   # replaced, not edited in place


def test_a_live_caller_tracks_frames_while_keyframe_flows_run_on_other_threads():
    """While a keyframe pair's flows run on the estimator's threads, the odometry calls ``interleave`` every few
    milliseconds (a frame that arrived is tracked at once), all at the yield point just passed, and hands back
    the pair's correspondences unchanged; a caller without ``interleave`` just waits."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from vigs_core.frontend.odometry import DenseOdometry
    from vigs_core.solver import Intrinsics

    odo = DenseOdometry(Intrinsics(150.0, 150.0, W / 2, H / 2), W, H)
    rng = np.random.default_rng(0)
    a = cv2.GaussianBlur((rng.random((H, W)) * 255).astype(np.uint8), (5, 5), 1.5)
    b = np.roll(a, 3, axis=1)
    expected = odo.estimator.estimate_pair(a, b)
    calls = []
    odo.interleave = lambda: calls.append(odo.yield_points)
    odo.in_keyframe_work, odo.yield_points = True, 7
    release = threading.Event()
    with ThreadPoolExecutor(1) as pool:   # a pair whose flows take 50 ms or more
        job = pool.submit(lambda: (release.wait(), odo.estimator.estimate_pair(a, b))[1])
        threading.Timer(0.05, release.set).start()
        got = odo._wait(job)
    assert len(calls) >= 5 and set(calls) == {7} and odo.yield_points == 7
    for g, e in zip(got, expected):
        np.testing.assert_array_equal(g.target, e.target)
        np.testing.assert_array_equal(g.weight, e.weight)
    odo.interleave = None
    assert odo._wait(odo.estimator.submit_pair(a, b))[0].target.shape == expected[0].target.shape
