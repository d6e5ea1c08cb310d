"""Issue 9 "done when" (1): a synthetic sequence with a loop and injected drift. Loop closure finds the revisit,
PGBA (on its worker thread) removes most of the drift including scale, and the Gaussian map anchored to the
keyframes follows the corrections in one batch."""
import math

import numpy as np
import torch

from loop_synthetic import cast, circle_sequence, drifted_chain, room
from vigs_core.camera import CameraModel
from vigs_core.frontend import DISFlowEstimator, PixelGrid
from vigs_core.loop.apply import apply_to_mapper, corrected_pose, corrections_for
from vigs_core.loop.closure import LoopClosure
from vigs_core.loop.config import LoopConfig
from vigs_core.loop.detection import KeyframeView
from vigs_core.loop.two_view import TwoViewCorrespondences, edge_information
from vigs_core.mapping.mapper import GaussianMapper, MapperConfig
from vigs_core.solver import Intrinsics

W, H = 160, 120
INTR = Intrinsics(100.0, 100.0, 79.5, 59.5)
GRID = PixelGrid(W, H, 8)
N = 66            # keyframes, 6 deg apart on a circle: keyframe 60 is back at keyframe 0


def correspondences(est, a, b):
    c = est.estimate(a, b)
    return TwoViewCorrespondences(torch.from_numpy(c.target), torch.from_numpy(c.weight.astype(np.float64)))


def test_loop_closure_removes_drift_and_the_map_follows():
    torch.set_num_threads(1)
    planes = room()
    truth, images, true_depths = circle_sequence(N, W, H, INTR.fx, GRID.stride)
    # monocular-like drift: mostly scale (0.6% per keyframe, 1.4x after the loop), some yaw, translation noise
    est, sigma = drifted_chain(truth, rot_per_step=0.0015, log_scale_per_step=0.006, trans_noise=0.002)
    depths = [true_depths[k] * sigma[k] for k in range(N)]
    flow = DISFlowEstimator(GRID)
    closure = LoopClosure(LoopConfig(asynchronous=True), DISFlowEstimator(GRID), INTR)
    views: list[KeyframeView] = []
    for k in range(N):
        view = KeyframeView.from_depth(k, images[k], est[k], depths[k])
        info = None
        if k > 0:  # odometry edge covariance from the dense correspondences of the pair, like the frontend's
            z = torch.linalg.inv(est[k - 1]) @ est[k]
            info = {k - 1: edge_information(z, depths[k - 1], depths[k], correspondences(flow, images[k - 1], images[k]),
                                            correspondences(flow, images[k], images[k - 1]), GRID, INTR)}
        closure.add_keyframe(view, views, info)
        views.append(view)
        closure.start_pgba({v.id: v.T_WC for v in views})
    first = closure.wait()
    # the loops accepted after the first PGBA started (or all, if the worker found them after the last keyframe)
    second = closure.wait() if closure.start_pgba({v.id: v.T_WC for v in views}) else None
    result = second or first
    assert result is not None
    closure.close()

    stats = closure.stats
    assert stats.loops_found >= 1 and stats.pgba_runs >= 1 and stats.pgba_seconds
    for old, new in stats.accepted_pairs:   # every accepted loop is a true revisit
        assert new - old >= 55
        assert float((truth[old, :3, 3] - truth[new, :3, 3]).norm()) < 0.3
        assert math.degrees(math.acos((float(torch.trace(truth[old, :3, :3].T @ truth[new, :3, :3])) - 1) / 2)) < 15
    corrections = corrections_for(range(N), result.corrections)
    fixed = [corrected_pose(corrections[k], est[k]) for k in range(N)]
    pos_before = (est[:, :3, 3] - truth[:, :3, 3]).norm(dim=1)
    pos_after = (torch.stack([T for T, _ in fixed])[:, :3, 3] - truth[:, :3, 3]).norm(dim=1)
    rmse_before, rmse_after = pos_before.pow(2).mean().sqrt(), pos_after.pow(2).mean().sqrt()
    assert rmse_before > 0.2
    assert rmse_after < 0.3 * rmse_before, (float(rmse_before), float(rmse_after))
    # the depth scale of the last keyframe is brought back towards the truth (estimated depth = sigma x true)
    assert abs(math.log(sigma[-1] * fixed[-1][1])) < 0.3 * abs(math.log(sigma[-1]))

    # the map: Gaussians anchored to every 6th keyframe, made from the drifted poses and depths
    camera = CameraModel(W, H, INTR.fx, INTR.fy, INTR.cx, INTR.cy)
    mapper = GaussianMapper(MapperConfig(iterations=0, render_scale=0.25, init_stride=2), camera)
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pix = np.stack((uu.ravel(), vv.ravel()), -1)
    anchors = list(range(0, N, 6))
    for k in anchors:
        depth = cast(planes, truth[k], pix, INTR, shade=False)[0].reshape(H, W) * float(sigma[k])
        mapper.add_keyframe(k, est[k], np.repeat(images[k][..., None], 3, -1), depth)
    mapper.process_pending()
    before = mapper.snapshot()

    def true_points(gmap):
        """Where each Gaussian belongs: its anchor-camera coordinates (drifted units / sigma) seen from the truth."""
        out = torch.empty_like(gmap.means, dtype=torch.float64)
        for k in anchors:
            rows = before.anchor_ids == k
            local = (before.means[rows].double() - est[k, :3, 3]) @ est[k, :3, :3] / sigma[k]
            out[rows] = local @ truth[k, :3, :3].T + truth[k, :3, 3]
        return out

    goal = true_points(before)
    apply_to_mapper(mapper, {k: fixed[k] for k in anchors})
    assert mapper.pending() == 1  # one batch
    mapper.process_pending()
    after = mapper.snapshot()
    assert torch.equal(after.ids, before.ids) and torch.equal(after.colors, before.colors)
    err_before = (before.means.double() - goal).norm(dim=1)
    err_after = (after.means.double() - goal).norm(dim=1)
    assert float(err_after.median()) < 0.3 * float(err_before.median())


def test_close_can_discard_the_queued_jobs_and_waits_for_the_running_one():
    """A node shutting down stops after the running job: the backlog is dropped, not searched (CI stalled on it)."""
    import threading

    closure = LoopClosure(LoopConfig(asynchronous=True), DISFlowEstimator(GRID), INTR)
    started, release = threading.Event(), threading.Event()
    finished = []

    def blocking_information():
        started.set()
        release.wait(10)
        finished.append(True)
        return None

    _, images, depths = circle_sequence(4, W, H, INTR.fx, GRID.stride)
    views = [KeyframeView.from_depth(k, images[k], torch.eye(4, dtype=torch.float64), depths[k]) for k in range(4)]
    closure.add_keyframe(views[0], [], blocking_information)
    assert started.wait(10)
    for k in range(1, 4):
        closure.add_keyframe(views[k], views[:k])
    threading.Timer(0.2, release.set).start()
    assert closure.close(discard_queued=True) == 3
    assert finished == [True]                   # the running job was finished, not cut
    assert closure.graph.ids == [0]           # the three queued ones never ran


def test_a_lagging_worker_thread_queues_views_without_their_images():
    """The detector keeps a view's image and disparities when it is queued (spilled beyond the resident count), so
    the jobs waiting for a stalled worker hold neither; detection then reads them back."""
    import gc
    import threading
    import weakref

    from vigs_core.spill import SpillConfig

    closure = LoopClosure(LoopConfig(asynchronous=True, images=SpillConfig(resident=1)), DISFlowEstimator(GRID), INTR)
    started, release = threading.Event(), threading.Event()

    def blocking_information():
        started.set()
        release.wait(10)
        return None

    _, pristine, depths = circle_sequence(5, W, H, INTR.fx, GRID.stride)   # cached: the test's own copies below
    images = [im.copy() for im in pristine]
    refs = [weakref.ref(im) for im in images]
    bare: list[KeyframeView] = []
    try:
        for k in range(5):
            view = KeyframeView.from_depth(k, images[k], torch.eye(4, dtype=torch.float64), depths[k])
            closure.add_keyframe(view, bare, blocking_information if k == 0 else None)
            bare.append(KeyframeView(k, None, view.T_WC, None))
            assert started.wait(10)
        del images, view
        gc.collect()
        assert [r() is None for r in refs] == [True, True, True, True, False]   # the newest stays resident
        release.set()
        closure.wait()
        assert closure.graph.ids == [0, 1, 2, 3, 4]
        for k in range(5):
            assert np.array_equal(closure.detector.image(bare[k]), pristine[k])
            assert torch.allclose(closure.detector.depth(bare[k]), depths[k].double())
    finally:
        release.set()
        closure.close()
