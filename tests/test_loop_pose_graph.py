"""Sim(3) pose-graph optimisation: exact Jacobians, drift removal on a loop, robustness to a bad loop edge."""
import math

import numpy as np
import scipy.sparse
import torch

from vigs_core.geometry import sim3_exp, sim3_from_srt, sim3_inverse, sim3_log, so3_exp
from vigs_core.loop import PoseGraph, PoseGraphConfig, optimize_pose_graph
from vigs_core.loop.pose_graph import _residuals, _solve_spd

D = torch.float64


def circle_poses(n=40, radius=3.0):
    """Ground-truth camera poses on a circle, looking outwards, unit scale."""
    angles = torch.arange(n, dtype=D) * (2 * math.pi / n)
    rot = so3_exp(torch.stack((torch.zeros(n, dtype=D), torch.zeros(n, dtype=D), angles), 1))
    trans = torch.stack((radius * torch.cos(angles), radius * torch.sin(angles), 0.1 * torch.sin(3 * angles)), 1)
    return sim3_from_srt(torch.ones(n, dtype=D), rot, trans)


def odometry_graph(truth, drift_rot=0.01, drift_scale=0.01, seed=0):
    """Chain edges from the truth; the initial poses integrate drifting odometry (rotation + scale drift)."""
    n = truth.shape[0]
    i = torch.arange(n - 1)
    j = i + 1
    z = PoseGraph.relative(truth, i, j)
    gen = torch.Generator().manual_seed(seed)
    drift = torch.zeros(n - 1, 7, dtype=D)
    drift[:, 5] = drift_rot
    drift[:, 6] = drift_scale
    drift[:, :3] = 0.01 * torch.randn(n - 1, 3, generator=gen, dtype=D)
    noisy = z @ sim3_exp(drift)
    poses = [truth[0]]
    for k in range(n - 1):
        poses.append(poses[-1] @ noisy[k])
    return torch.stack(poses), i, j, z


def test_residual_jacobian_matches_numerical():
    truth = circle_poses(6)
    poses, _, _, _ = odometry_graph(truth)
    # Disjoint node pairs, so perturbing all j nodes at once moves each edge through one node only.
    i, j = torch.tensor([0, 2, 4]), torch.tensor([1, 3, 5])
    z = PoseGraph.relative(truth, i, j)
    info = torch.eye(7, dtype=D).expand(3, 7, 7).clone()
    graph = PoseGraph(poses, i, j, z @ sim3_exp(0.1 * torch.ones(3, 7, dtype=D)), info)
    r0 = _residuals(graph, poses)
    # Analytic d r / d d_j from the module's formula.
    from vigs_core.geometry import sim3_adjoint, sim3_left_jacobian_inv

    jj = sim3_left_jacobian_inv(r0) @ sim3_adjoint(sim3_inverse(poses[i] @ graph.measurements))
    eps = 1e-6
    for k in range(7):
        d = torch.zeros(7, dtype=D)
        d[k] = eps
        plus, minus = poses.clone(), poses.clone()
        plus[j] = sim3_exp(d) @ poses[j]
        minus[j] = sim3_exp(-d) @ poses[j]
        num = (_residuals(graph, plus) - _residuals(graph, minus)) / (2 * eps)
        np.testing.assert_allclose(num.numpy(), jj[:, :, k].numpy(), atol=1e-7)


def test_loop_edge_removes_drift_including_scale():
    truth = circle_poses(40)
    poses, i, j, z = odometry_graph(truth)
    # The loop edge: last keyframe to the first, measured exactly.
    li, lj = torch.tensor([39]), torch.tensor([0])
    graph = PoseGraph(
        poses,
        torch.cat((i, li)),
        torch.cat((j, lj)),
        torch.cat((z, PoseGraph.relative(truth, li, lj))),
        torch.eye(7, dtype=D).expand(40, 7, 7).clone() * torch.cat((torch.ones(39), torch.tensor([100.0])))[:, None, None].to(D),
        robust=torch.cat((torch.zeros(39, dtype=torch.bool), torch.ones(1, dtype=torch.bool))),
    )
    err_before = (poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1)
    result = optimize_pose_graph(graph, PoseGraphConfig(huber_delta=0.0))
    err_after = (result.poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1)
    assert result.final_cost < 0.05 * result.initial_cost
    assert err_after.max() < 0.2 * err_before.max()
    scale_after = torch.exp(sim3_log(result.poses)[:, 6])
    assert (scale_after[-1] - 1).abs() < 0.2 * (torch.exp(sim3_log(poses)[-1, 6]) - 1).abs()
    assert torch.equal(result.poses[0], poses[0])  # the gauge node stays put


def test_huber_limits_a_false_loop_edge():
    """Precise, redundant odometry (skip edges) against one false loop edge: Huber caps its pull."""
    truth = circle_poses(20)
    poses, i, j, z = odometry_graph(truth, drift_rot=0.0, drift_scale=0.0)
    si, sj = torch.arange(18), torch.arange(18) + 2
    wrong = sim3_exp(torch.tensor([2.0, 0, 0, 0, 0, 1.0, 0.3], dtype=D))[None]
    ei = torch.cat((i, si, torch.tensor([19])))
    ej = torch.cat((j, sj, torch.tensor([5])))
    meas = torch.cat((z, PoseGraph.relative(truth, si, sj), wrong))
    info = (torch.eye(7, dtype=D) * 1e4).expand(len(ei), 7, 7).clone()
    info[-1] = torch.eye(7, dtype=D) * 100
    robust = torch.zeros(len(ei), dtype=torch.bool)
    robust[-1] = True
    plain = optimize_pose_graph(PoseGraph(poses, ei, ej, meas, info), PoseGraphConfig(huber_delta=0.0))
    huber = optimize_pose_graph(PoseGraph(poses, ei, ej, meas, info, robust=robust), PoseGraphConfig(huber_delta=1.0))
    err_plain = (plain.poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()
    err_huber = (huber.poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()
    assert err_plain > 0.5  # the false edge wrecks the unprotected solution
    assert err_huber < 0.1


def test_scale_prior_keeps_metric_nodes_at_their_scale():
    """Metric keyframes (scale observed by the IMU) with rotation drift only and a loop edge whose scale is 10%
    off: without the node scale prior the loop's scale spreads into every node; with it the nodes keep scale 1
    while the loop still removes the rotation drift."""
    truth = circle_poses(40)
    poses, i, j, z = odometry_graph(truth, drift_rot=0.01, drift_scale=0.0)
    li, lj = torch.tensor([39]), torch.tensor([0])
    wrong_scale = PoseGraph.relative(truth, li, lj) @ sim3_exp(torch.tensor([0, 0, 0, 0, 0, 0, math.log(0.9)], dtype=D))
    info = torch.eye(7, dtype=D).expand(40, 7, 7).clone()
    info[-1] *= 100.0
    args = (poses, torch.cat((i, li)), torch.cat((j, lj)), torch.cat((z, wrong_scale)), info)
    free = optimize_pose_graph(PoseGraph(*args), PoseGraphConfig(huber_delta=0.0))
    held = optimize_pose_graph(PoseGraph(*args, scale_information=torch.full((40,), 1e6, dtype=D)),
                               PoseGraphConfig(huber_delta=0.0))
    scales_free = torch.exp(sim3_log(free.poses)[:, 6])
    scales_held = torch.exp(sim3_log(held.poses)[:, 6])
    assert (scales_free - 1).abs().max() > 0.03
    assert (scales_held - 1).abs().max() < 1e-3
    err_before = (poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()
    err_held = (held.poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()
    assert err_held < 0.3 * err_before
    assert held.final_cost < held.initial_cost


def test_gravity_prior_keeps_roll_and_pitch_while_a_loop_corrects_yaw_and_position():
    """Metric keyframes (roll and pitch observed by the IMU) with yaw drift, and a loop edge whose relative
    rotation is 3 deg tilted about x: without the gravity prior the tilt spreads into the nodes' up directions;
    with it every node keeps its up direction (to 0.1 deg) while the loop still corrects the position drift."""
    truth = circle_poses(40)
    poses, i, j, z = odometry_graph(truth, drift_rot=0.01, drift_scale=0.0)
    li, lj = torch.tensor([39]), torch.tensor([0])
    tilted = PoseGraph.relative(truth, li, lj) @ sim3_exp(torch.tensor([0, 0, 0, math.radians(3), 0, 0, 0], dtype=D))
    info = torch.eye(7, dtype=D).expand(40, 7, 7).clone()
    info[-1] *= 100.0
    args = (poses, torch.cat((i, li)), torch.cat((j, lj)), torch.cat((z, tilted)), info)
    up = poses[:, 2, :3] / poses[:, :3, 0].norm(dim=-1, keepdim=True)

    def tilt_deg(result):
        new = result.poses[:, 2, :3] / result.poses[:, :3, 0].norm(dim=-1, keepdim=True)
        return torch.rad2deg(torch.acos((new * up).sum(-1).clamp(max=1.0))).max()

    free = optimize_pose_graph(PoseGraph(*args), PoseGraphConfig(huber_delta=0.0))
    held = optimize_pose_graph(PoseGraph(*args, gravity_information=torch.full((40,), 1e8, dtype=D)),
                               PoseGraphConfig(huber_delta=0.0))
    assert tilt_deg(free) > 1.0 and tilt_deg(held) < 0.1, (tilt_deg(free), tilt_deg(held))
    err_before = (poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()
    assert (held.poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max() < 0.5 * err_before
    assert held.final_cost < held.initial_cost


def test_the_damped_system_solve_returns_the_step_or_none_when_singular():
    """The symmetric-mode factorisation gives ``-A^-1 b`` for a positive definite ``A`` and None (damp more)
    where ``A`` is singular, instead of a step of NaNs."""
    rng = np.random.default_rng(0)
    M = rng.normal(size=(14, 14))
    A = scipy.sparse.csc_matrix(M @ M.T + 14 * np.eye(14))
    b = rng.normal(size=14)
    assert np.allclose(_solve_spd(A, b).numpy(), -np.linalg.solve(A.toarray(), b), atol=1e-12)
    singular = A.toarray()
    singular[3, :] = singular[:, 3] = 0.0
    assert _solve_spd(scipy.sparse.csc_matrix(singular), b) is None
