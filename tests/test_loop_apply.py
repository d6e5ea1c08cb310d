"""Applying PGBA corrections: the frontend's keyframes, disparities and frames move as the Sim(3) says; the
driver runs loop closure beside a DenseOdometry (detection and PGBA in a worker process or thread) and corrects
it; PGBA never blocks the caller; the worker process hands its errors to the caller."""
import math
import time

import numpy as np
import pytest
import torch

from loop_synthetic import circle_sequence, drifted_chain
from test_loop_pose_graph import circle_poses, odometry_graph
from vigs_core.frontend import DISFlowEstimator, PixelGrid
from vigs_core.frontend.correspondence import Correspondences
from vigs_core.frontend.keyframe_changes import KeyframeTable
from vigs_core.frontend.odometry import DenseOdometry, Keyframe, _Frame  # the records the hook edits
from vigs_core.geometry import se3_inverse, sim3_act, sim3_exp
from vigs_core.loop import (LoopClosure, LoopClosureDriver, LoopConfig, LoopEdge, apply_to_odometry,
                            corrected_pose, corrections_for)
from vigs_core.loop.config import LoopDetectionConfig
from vigs_core.loop.driver import keyframe_views
from vigs_core.loop.process import LoopClosureProcess
from vigs_core.solver import Intrinsics, pixel_rays

D = torch.float64
W, H = 160, 120
INTR = Intrinsics(100.0, 100.0, 79.5, 59.5)
GRID = PixelGrid(W, H, 8)


def keyframe_points(odo, k):
    """World points (P, 3) of keyframe k's grid from its pose and disparities."""
    kf = odo.keyframes[k]
    cam = pixel_rays(torch.from_numpy(odo.grid.coords()), odo.intr) / kf.disp[:, None]
    return cam @ se3_inverse(kf.pose)[:3, :3].T + se3_inverse(kf.pose)[:3, 3]


def small_odometry(n=4):
    odo = DenseOdometry(INTR, W, H)
    gen = torch.Generator().manual_seed(3)
    image = np.zeros((H, W), dtype=np.uint8)
    for k in range(n):
        T_wc = sim3_exp(torch.tensor([0.3 * k, 0.05 * k, 0.0, 0.0, 0.1 * k, 0.0, 0.0], dtype=D))
        disp = 0.2 + torch.rand(GRID.size, generator=gen, dtype=D)
        odo.keyframes[k] = Keyframe(k, 100 * k, image, se3_inverse(T_wc), disp)
        for m in range(2):  # the keyframe's frame and one tracked frame after it
            rel = torch.eye(4, dtype=D) if m == 0 else se3_inverse(sim3_exp(torch.tensor([0.1, 0, 0, 0, 0.02, 0, 0], dtype=D)))
            odo.frames.append(_Frame(100 * k + m, odo._pose_rows, ref=k, rel=rel, odom=rel @ odo.keyframes[k].pose,
                                     keyframe=m == 0))
    return odo


def test_apply_to_odometry_moves_keyframes_depths_and_frames_by_the_similarity():
    odo = small_odometry()
    output = odo.frames[-1].odom
    points = {k: keyframe_points(odo, k) for k in odo.keyframes}
    _, frame_poses = odo.final_frame_poses()
    centres = se3_inverse(frame_poses)[:, :3, 3]
    C = {0: torch.eye(4, dtype=D), 1: sim3_exp(torch.tensor([0.2, -0.1, 0.05, 0.02, 0.1, -0.05, 0.3], dtype=D)),
         2: sim3_exp(torch.tensor([0.1, 0.3, 0.0, 0.0, -0.1, 0.05, -0.2], dtype=D))}
    updates = apply_to_odometry(odo, C)
    assert set(updates) == {0, 1, 2, 3}  # keyframe 3 is newer than the snapshot: it gets keyframe 2's correction
    for k in odo.keyframes:
        Ck = C[min(k, 2)]
        np.testing.assert_allclose(keyframe_points(odo, k).numpy(), sim3_act(Ck, points[k]).numpy(), atol=1e-9)
        T, c = updates[k]
        np.testing.assert_allclose(T.numpy(), se3_inverse(odo.keyframes[k].pose).numpy(), atol=1e-12)
        assert math.isclose(c, float(torch.linalg.det(Ck[:3, :3])) ** (1 / 3), rel_tol=1e-9)
    _, after = odo.final_frame_poses()
    refs = [f.ref for f in odo.frames]
    for n, k in enumerate(refs):   # every frame keeps its place relative to its keyframe
        np.testing.assert_allclose(se3_inverse(after[n])[:3, 3].numpy(), sim3_act(C[min(k, 2)], centres[n:n + 1])[0].numpy(),
                                   atol=1e-9)
    # the motion model reads the latest frames in the corrected map; their causal poses stay as output
    np.testing.assert_allclose(odo._current_pose(odo.frames[-1]).numpy(), after[-1].numpy(), atol=1e-12)
    assert torch.equal(odo.frames[-1].odom, output) and not torch.allclose(output, after[-1])


def test_corrected_poses_are_rigid_though_the_corrections_are_a_little_off():
    """Keyframes take one loop correction after another: the corrected rotation is projected onto SO(3), so the
    rounding of each Sim(3) product does not pile up in the keyframe poses."""
    from vigs_core.loop.apply import corrected_poses

    strain = torch.tensor([[1.0, 0.5, 0.0], [0.5, -1.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    T_WC = torch.eye(4, dtype=torch.float64)
    for k in range(200):
        C = sim3_exp(torch.tensor([0.1, -0.2, 0.05, 0.02, -0.01, 0.03, 0.01], dtype=torch.float64))
        C[:3, :3] = C[:3, :3] @ (torch.eye(3, dtype=torch.float64) + 1e-6 * strain)   # slightly off a rotation
        T_WC, c = corrected_poses(C, T_WC)
        R = T_WC[:3, :3]
        assert float((R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max()) < 1e-12, k


def test_corrections_for_leaves_out_older_ids():
    C = {3: torch.eye(4, dtype=D), 4: 2 * torch.eye(4, dtype=D)}
    out = corrections_for([1, 3, 4, 7], C)
    assert sorted(out) == [3, 4, 7] and torch.equal(out[7], C[4])


def test_pgba_runs_beside_the_caller():
    """A large pose graph: queuing PGBA returns at once, the result arrives later through poll()."""
    torch.set_num_threads(1)
    truth = circle_poses(160)
    poses, _, _, _ = odometry_graph(truth, drift_rot=0.002, drift_scale=0.002)
    closure = LoopClosure(LoopConfig(asynchronous=True), DISFlowEstimator(GRID), INTR)
    for k in range(160):
        closure.graph.add_keyframe(k)
    rel = torch.linalg.inv(truth[0]) @ truth[159]
    closure.graph.add_loop(LoopEdge(0, 159, rel, torch.eye(7, dtype=D) * 1e4, 1.0))
    closure._pending_loops = 1  # as the detector does on acceptance
    t0 = time.perf_counter()
    assert closure.start_pgba({k: poses[k] for k in range(160)})
    queued = time.perf_counter() - t0
    assert closure.poll() is None   # the caller has control back while the worker optimises
    assert not closure.start_pgba({k: poses[k] for k in range(160)})  # one PGBA at a time
    result = closure.wait()
    assert result is not None and result.seconds > queued
    assert closure.poll() is None  # handed out once
    err_before = (poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()
    fixed = torch.stack([corrected_pose(result.corrections[k], poses[k])[0] for k in range(160)])
    assert (fixed[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max() < 0.3 * err_before
    closure.close()


class BrokenInformation:
    """An odometry-edge information source that fails on the worker (picklable, for the worker process)."""

    def __call__(self):
        raise ValueError("broken information")


def test_worker_process_hands_its_errors_to_the_caller():
    odo = small_odometry(2)
    views = keyframe_views([odo.keyframes[0], odo.keyframes[1]], [1.0, 1.0], [True, True], [True, True])
    # the child starts at the second keyframe (the keyframe gap): the first one's messages wait for it
    closure = LoopClosureProcess(LoopConfig(detection=LoopDetectionConfig(min_keyframe_gap=2)), GRID,
                                 DISFlowEstimator(GRID).config, INTR)
    closure.add_keyframe(views[0], [])
    assert not closure._channel.started and closure.wait() is None
    closure.add_keyframe(views[1], views[:1], BrokenInformation())
    assert closure._channel.started
    with pytest.raises(RuntimeError, match="broken information"):
        closure.wait()
    assert not closure.pending and closure.poll() is None   # reported once; the worker goes on
    closure.close()
    assert closure.stats.loops_found == 0


def test_a_worker_process_is_started_only_once_loops_are_possible():
    odo = small_odometry(2)
    views = keyframe_views([odo.keyframes[0], odo.keyframes[1]], [1.0, 1.0], [True, True], [True, True])
    closure = LoopClosureProcess(LoopConfig(), GRID, DISFlowEstimator(GRID).config, INTR)   # keyframe gap 55
    closure.add_keyframe(views[0], [])
    closure.add_keyframe(views[1], views[:1])
    assert not closure.pending and closure.wait() is None and closure.poll() is None
    closure.close()
    assert closure._channel.process.pid is None and closure.stats.loops_found == 0
    assert closure.stats.process_peak_rss_mb is None   # no process, no memory to report


def test_a_dead_worker_process_is_reported():
    closure = LoopClosureProcess(LoopConfig(detection=LoopDetectionConfig(min_keyframe_gap=0)), GRID,
                                 DISFlowEstimator(GRID).config, INTR)
    closure._channel.process.kill()
    closure._channel.process.join()
    with pytest.raises(RuntimeError, match="loop-closure process ended"):
        closure.wait()


@pytest.mark.parametrize("process", [True, False], ids=["process", "thread"])
def test_driver_closes_the_loop_of_a_drifting_odometry(process):
    torch.set_num_threads(1)
    n = 66
    truth, images, true_depths = circle_sequence(n, W, H, INTR.fx, GRID.stride)
    est, sigma = drifted_chain(truth, rot_per_step=0.0015, log_scale_per_step=0.006, trans_noise=0.002)
    odo = DenseOdometry(INTR, W, H)
    driver = LoopClosureDriver(LoopConfig(process=process), odo)
    assert isinstance(driver.closure, LoopClosureProcess) == process
    flow = DISFlowEstimator(GRID)
    disp0 = [1.0 / (true_depths[k] * sigma[k]) for k in range(n)]
    for k in range(n):
        # the frontend's state after each keyframe's BA: the drifting odometry continues from the current
        # (possibly corrected) previous keyframe, in its current depth units
        T_wc, disp = est[0], disp0[0]
        if k > 0:
            prev = odo.keyframes[k - 1]
            f = float((disp0[k - 1] / prev.disp).median())   # depth scale applied to k-1 by corrections so far
            rel = torch.linalg.inv(est[k - 1]) @ est[k]
            rel[:3, 3] *= f
            T_wc, disp = se3_inverse(prev.pose) @ rel, disp0[k] / f
        odo.keyframes[k] = Keyframe(k, 50_000_000 * k, images[k], se3_inverse(T_wc), disp)
        odo.frames.append(_Frame(50_000_000 * k, odo._pose_rows, ref=k, rel=torch.eye(4, dtype=D),
                                 odom=se3_inverse(T_wc), keyframe=True))
        if k > 0:
            for a, b in ((k - 1, k), (k, k - 1)):
                c = flow.estimate(images[a], images[b])
                odo.edges[(a, b)] = Correspondences(c.target, c.weight, c.mean_flow)
        driver.step()
    driver.finish()
    rep = driver.report()
    assert rep["loops_found"] >= 1 and rep["corrections_applied"] >= 1 and rep["pgba_runs"] >= 1
    _, T_cw = odo.keyframe_poses()
    err_before = (est[:, :3, 3] - truth[:, :3, 3]).norm(dim=1)
    err_after = (se3_inverse(T_cw)[:, :3, 3] - truth[:, :3, 3]).norm(dim=1)
    assert err_after.pow(2).mean().sqrt() < 0.3 * err_before.pow(2).mean().sqrt()
    # disparities follow the scale correction: the last keyframe's depth is close to metric again
    depth_ratio = (1.0 / odo.keyframes[n - 1].disp) / true_depths[n - 1]
    assert abs(math.log(float(depth_ratio.median()))) < 0.3 * abs(math.log(float(sigma[-1])))


def test_loop_edges_follow_the_depth_units_of_applied_corrections():
    """A loop measured before keyframe 1's depths were rescaled by 2 relates X_b = X_b' / 2: the graph uses
    ``Z D(1/2)``."""
    from vigs_core.loop import KeyframePoseGraph

    graph = KeyframePoseGraph()
    graph.add_keyframe(0)
    graph.add_keyframe(1)
    Z = sim3_exp(torch.tensor([0.3, -0.2, 0.1, 0.05, 0.1, -0.1, 0.2], dtype=D))
    graph.add_loop(LoopEdge(0, 1, Z, torch.eye(7, dtype=D), 1.0))
    poses = {0: torch.eye(4, dtype=D), 1: torch.eye(4, dtype=D)}
    before, _ = graph.build(poses)
    after, _ = graph.build(poses, {1: 2.0})
    X_b = torch.tensor([[0.4, -0.3, 2.0]], dtype=D)
    np.testing.assert_allclose(sim3_act(after.measurements[-1], 2.0 * X_b).numpy(),
                               sim3_act(before.measurements[-1], X_b).numpy(), atol=1e-12)


def test_a_loop_to_a_keyframe_from_before_the_initialisation_rescales_it_rather_than_bend_the_metric_part():
    """Keyframes 0-9 were created before the odometry was metric, and that part of the map (poses and depths) is
    9 % too large: a loop from metric keyframe 39 to keyframe 3 measures a relative scale of 1.09 and a
    translation 9 % long. Without a metric prior the early keyframes take the loop's scale; with a prior on
    every keyframe (the graph before per-keyframe flags) the loop bent the metric part instead."""
    from vigs_core.loop import KeyframePoseGraph
    from vigs_core.loop.config import LoopGraphConfig
    from vigs_core.loop.pgba import run_pgba
    from vigs_core.loop.pose_graph import PoseGraphConfig

    truth = circle_poses(40)
    k = 1.09
    estimate = truth.clone()
    estimate[:10, :3, 3] = truth[10, :3, 3] + k * (truth[:10, :3, 3] - truth[10, :3, 3])
    D = torch.diag(torch.tensor([k, k, k, 1.0], dtype=torch.float64))

    def shape_error(T: torch.Tensor, nodes: slice) -> float:
        """Largest change of a distance between two of the nodes against the truth (rigid-invariant)."""
        p, q = T[nodes, :3, 3], truth[nodes, :3, 3]
        return float((torch.cdist(p, p) - torch.cdist(q, q)).abs().max())

    def corrected(metric_from: int) -> torch.Tensor:
        graph = KeyframePoseGraph(LoopGraphConfig(sigma_metric_log_scale=0.002))   # a scale the IMU holds well
        for n in range(40):
            graph.add_keyframe(n, metric=n >= metric_from)
        graph.add_loop(LoopEdge(3, 39, D @ torch.linalg.inv(truth[3]) @ truth[39],
                                1e4 * torch.eye(7, dtype=torch.float64), 1.0))
        pg, ids = graph.build({n: estimate[n] for n in range(40)})
        assert torch.equal(pg.scale_information > 0, torch.arange(40) >= metric_from)
        result = run_pgba(pg, ids, 1, PoseGraphConfig(huber_delta=0.0))
        return torch.stack([result.corrections[n] @ estimate[n] for n in range(40)])

    flagged, all_held = corrected(10), corrected(0)
    assert shape_error(flagged, slice(None)) < 0.5 * shape_error(estimate, slice(None))
    assert shape_error(all_held, slice(None)) > 0.8 * shape_error(estimate, slice(None))
    assert shape_error(flagged, slice(10, None)) < 0.4 * shape_error(all_held, slice(10, None))


def test_driver_views_follow_keyframes_re_expressed_outside_the_window():
    """The visual-inertial world alignment replaces every keyframe's pose and scales its depths, also of keyframes
    that left the window long ago; loop detection must see them in the new (metric) world, not a stale cache."""
    odo = small_odometry(4)
    odo.graph.keyframes = [3]   # only the newest keyframe is still in the window
    driver = LoopClosureDriver(LoopConfig(asynchronous=False), odo)
    before = driver._current_views()
    s = 0.25   # the alignment's scale: world points x -> s x, disparities / s
    kf = odo.keyframes[0]
    T_wc = se3_inverse(kf.pose)
    T_wc[:3, 3] *= s
    kf.pose = se3_inverse(T_wc)
    kf.rescale_depth(s)
    after = driver._current_views()
    torch.testing.assert_close(after[0].T_WC[:3, 3], s * before[0].T_WC[:3, 3])
    torch.testing.assert_close(after[0].depth, before[0].depth * s)   # still has its disparities: carried
    assert after[0].depth_scale == s
    assert 1 not in after and driver._views[1][4].T_WC is before[1].T_WC   # unchanged: not rebuilt


def test_final_poses_spread_the_next_keyframes_correction_and_follow_a_similarity():
    """A frame halfway between keyframe a and the keyframe b made next gets half of the correction BA applied to b
    (tracked 1.0 m from a, final 0.9 m: the frame tracked at 0.55 m ends at 0.50 m); a uniform loop correction
    (scale 2) moves all final poses by that similarity, tracked relative poses included."""

    def at(x):   # world->camera pose of an unrotated camera centred at (x, 0, 0)
        T = torch.eye(4, dtype=D)
        T[0, 3] = -x
        return T

    odo = DenseOdometry(INTR, W, H)
    image = np.zeros((H, W), dtype=np.uint8)
    disp = torch.full((GRID.size,), 0.5, dtype=D)
    odo.keyframes[0] = Keyframe(0, 0, image, at(0.0), disp)
    odo.keyframes[1] = Keyframe(1, 1000, image, at(0.9), disp, tracked=(0, at(1.0)))
    rows = odo._pose_rows
    odo.frames += [_Frame(0, rows, ref=0, rel=at(0.0), keyframe=True), _Frame(500, rows, ref=0, rel=at(0.55)),
                   _Frame(1000, rows, ref=1, rel=at(0.0), keyframe=True), _Frame(1500, rows, ref=1, rel=at(0.3))]
    _, poses = odo.final_frame_poses()
    centres = se3_inverse(poses)[:, :3, 3]
    np.testing.assert_allclose(centres[:, 0].numpy(), [0.0, 0.50, 0.9, 1.2], atol=1e-12)
    assert float(centres[:, 1:].abs().max()) < 1e-12
    C = sim3_exp(torch.tensor([0.1, 0.2, 0.0, 0.0, 0.0, 0.3, math.log(2.0)], dtype=D))
    apply_to_odometry(odo, {0: C})
    _, after = odo.final_frame_poses()
    np.testing.assert_allclose(se3_inverse(after)[:, :3, 3].numpy(), sim3_act(C, centres).numpy(), atol=1e-12)


def test_the_worker_process_gets_images_and_disparities_once_each():
    """Through the driver, views go to the child when new or changed: image and disparities with a keyframe's first
    view, its disparities again once it has left the frontend's window (their last revision; the frontend drops
    them at the next frame), never for the revisions of BA inside the window; a uniform rescaling travels as the
    depth scale alone."""
    odo = small_odometry(5)
    keyframes = dict(odo.keyframes)
    odo.keyframes = KeyframeTable()
    for k in range(3):
        odo.keyframes[k] = keyframes[k]
    odo.graph.keyframes = [0, 1, 2]
    driver = LoopClosureDriver(LoopConfig(detection=LoopDetectionConfig(min_keyframe_gap=3)), odo)
    posted = []
    post = driver.closure._post
    driver.closure._post = lambda msg: (posted.append(msg), post(msg))

    def sent():   # (id, disparities?, image?, revision, depth scale) of the views posted since the last call
        out = [(v[0], v[2] is not None, v[4] is not None, v[5], v[6]) for m in posted if m[0] == "views"
               for v in m[1]]
        posted.clear()
        return out

    try:
        driver.step()
        assert sent() == [(0, True, True, 0, 1.0), (1, True, True, 0, 1.0), (2, True, True, 0, 1.0)]
        # keyframe 3 enters the window, 0 leaves it; BA re-estimated 1 and 2 (new pose and disparities)
        for k in (1, 2):
            kf = odo.keyframes[k]
            kf.pose = kf.pose.clone()
            kf.set_disparities(kf.disp * 1.01)
        odo.keyframes[3], odo.graph.keyframes = keyframes[3], [1, 2, 3]
        odo.keyframes.changes.note(0)   # as the frontend notes a keyframe leaving its window
        driver.step()
        assert sent() == [(0, True, False, 0, 1.0), (1, False, False, 1, 1.0), (2, False, False, 1, 1.0),
                          (3, True, True, 0, 1.0)]
        # the frontend dropped 0's disparities; a loop correction moves 0 and doubles its depths; 4 comes, 1 leaves
        kf = odo.keyframes[0]
        kf.disp = None
        kf.pose = kf.pose.clone()
        kf.rescale_depth(2.0)
        odo.keyframes[4], odo.graph.keyframes = keyframes[4], [2, 3, 4]
        odo.keyframes.changes.note(1)
        driver.step()
        assert sent() == [(0, False, False, 0, 2.0), (1, True, False, 1, 1.0), (4, True, True, 0, 1.0)]
        driver.finish()   # the child ran detection on all of it (keyframe 4 against 0 and 1) without an error
    finally:
        driver.closure.close()


def test_inertial_velocities_turn_and_scale_with_their_keyframes_corrections():
    """``v' = c R_c v`` for every keyframe with an inertial state, in one batch; ids without one are skipped."""
    from types import SimpleNamespace

    from vigs_core.loop import rotate_velocities
    C = {k: sim3_exp(torch.tensor([0.1 * k, 0.0, 0.2, 0.3, -0.1 * k, 0.05, 0.1 * k], dtype=D)) for k in range(3)}
    v = {k: torch.tensor([1.0, -2.0, 0.5 * k], dtype=D) for k in (0, 2)}
    states = {k: SimpleNamespace(velocity=v[k].clone()) for k in v}
    rotate_velocities(states, C)
    assert set(states) == {0, 2}
    for k in v:
        torch.testing.assert_close(states[k].velocity, C[k][:3, :3] @ v[k])   # C[:3, :3] = c R_c
        assert abs(float(states[k].velocity.norm() / v[k].norm()) - math.exp(0.1 * k)) < 1e-12
