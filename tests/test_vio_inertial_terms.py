"""Inertial terms inside dense BA: Jacobians in the solver's parameterisation, zero residual at the truth,
exact joint VI-BA convergence, and the IMU pulling visually degenerate problems towards the truth."""
import math

import numpy as np
import pytest
import torch

from vigs_core.geometry import se3_exp, se3_inverse, so3_exp
from vigs_core.imu.preintegration import preintegrate_between
from vigs_core.solver import BAConfig, EdgeSet, bundle_adjust
from vigs_core.vio.inertial_terms import AnchorPrior, InertialState, InertialTerms
from vio_synthetic import INTR, NOISE, T_CB, make_scenario, visual_problem

torch.set_num_threads(1)
F64 = dict(dtype=torch.float64)


def _state(sc, biases, log_scale=0.0, R_wg=None):
    return InertialState(sc.velocities.clone(), biases, torch.eye(3, **F64) if R_wg is None else R_wg,
                         torch.tensor(log_scale, **F64))


def _random_state(n, per_keyframe, seed):
    g = torch.Generator().manual_seed(seed)
    nb = n if per_keyframe else 1
    b = torch.cat((0.01 * torch.randn(nb, 3, generator=g, **F64), 0.05 * torch.randn(nb, 3, generator=g, **F64)), 1)
    return (torch.randn(n, 3, generator=g, **F64), b, so3_exp(0.3 * torch.randn(3, generator=g, **F64)),
            torch.tensor(0.2, **F64))


def _retract_full(terms, poses, state, dx):
    n = poses.shape[0]
    return se3_exp(dx[:6 * n].view(n, 6)) @ poses, terms.retract(state, dx[6 * n:])


@pytest.mark.parametrize("per_keyframe,estimate_bias", [(True, True), (False, True), (True, False)])
def test_jacobian_matches_central_differences(per_keyframe, estimate_bias):
    sc = make_scenario(n=4)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE, bias_gyro=np.array([0.01, 0.0, -0.01]))
    terms = InertialTerms(pre, T_CB, estimate_bias=estimate_bias, per_keyframe_bias=per_keyframe,
                          estimate_gravity=True, estimate_scale=True)
    v, b, R_wg, s = _random_state(4, per_keyframe, seed=3)
    state = InertialState(v, b, R_wg, s)
    # poses away from the truth so that every Jacobian block is exercised at a non-zero residual
    poses = se3_exp(0.05 * torch.randn(4, 6, generator=torch.Generator().manual_seed(5), **F64)) @ se3_inverse(sc.T_wc)
    r0, J = terms.jacobian(poses, state)
    N = 6 * 4 + terms.dim
    assert J.shape == (3, r0.shape[1], N)
    eps = 1e-6
    for k in range(N):
        dx = torch.zeros(N, **F64)
        dx[k] = eps
        rp = terms._residual_vector(terms.evaluate(*_retract_full(terms, poses, state, dx)))
        rm = terms._residual_vector(terms.evaluate(*_retract_full(terms, poses, state, -dx)))
        num = (rp - rm) / (2 * eps)
        assert torch.allclose(num, J[..., k], atol=2e-6 * (1 + J[..., k].abs().max())), f"column {k}"


def test_gradient_and_hessian_are_gauss_newton_of_the_cost():
    sc = make_scenario(n=3)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    v, b, _, _ = _random_state(3, True, seed=1)
    # with an anchor prior on keyframe 0 that disagrees with the state
    anchor = AnchorPrior(torch.tensor([True, False, False]), v + 0.1, b + 0.01, 0.05, torch.full((6,), 0.02, **F64))
    terms = InertialTerms(pre, T_CB, anchor=anchor)
    state = InertialState(v, b, torch.eye(3, **F64), torch.zeros((), **F64))
    poses = se3_inverse(sc.T_wc)
    H, g, cost = terms.linearize(poses, state)
    assert torch.allclose(H, H.T)
    assert float(torch.linalg.eigvalsh(H)[0]) > -1e-6 * float(H.diagonal().max())
    assert math.isclose(float(cost), float(terms.cost(poses, state)), rel_tol=1e-12)
    # the gradient is -dcost/dx: a small step along g lowers the cost at the predicted rate
    step = 1e-7 * g / g.norm()
    p1, s1 = _retract_full(terms, poses, state, step)
    decrease = float(cost - terms.cost(p1, s1))
    assert decrease == pytest.approx(float(g @ step), rel=1e-3)


def test_residual_vanishes_at_the_truth():
    sc = make_scenario(n=6, bias_gyro=(0.01, -0.02, 0.005), bias_acc=(0.1, 0.05, -0.1))
    b_true = torch.tensor(np.concatenate([sc.bias_gyro, sc.bias_acc]), **F64)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE, bias_gyro=sc.bias_gyro, bias_acc=sc.bias_acc)
    terms = InertialTerms(pre, T_CB)
    r, _ = terms.jacobian(se3_inverse(sc.T_wc), _state(sc, b_true.expand(6, 6).clone()))
    assert r[:, :3].abs().max() < 1e-5          # rad
    assert r[:, 3:9].abs().max() < 1e-5         # m/s, m
    assert r[:, 9:].abs().max() == 0.0
    # and a wrong velocity is seen
    bad = _state(sc, b_true.expand(6, 6).clone())
    bad.velocities[2] += 0.05
    r_bad, _ = terms.jacobian(se3_inverse(sc.T_wc), bad)
    assert r_bad[:, 3:6].abs().max() > 0.04


def _perturbed(sc, T_cw, disps, seed=1, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    n = T_cw.shape[0]
    xi = scale * torch.cat((0.03 * torch.randn(n, 3, generator=g, **F64),
                            0.01 * torch.randn(n, 3, generator=g, **F64)), 1)
    xi[0] = 0
    d = disps * (1 + 0.1 * scale * torch.randn(disps.shape, generator=g, **F64))
    v = sc.velocities + 0.1 * scale * torch.randn(n, 3, generator=g, **F64)
    return se3_exp(xi) @ T_cw, d, v


def test_joint_vi_ba_with_exact_data_converges_to_the_truth():
    sc = make_scenario(n=6, spacing_s=0.3, seed=2)
    T_true = se3_inverse(sc.T_wc)
    disps, coords, edges = visual_problem(T_true)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    terms = InertialTerms(pre, T_CB)
    T0, d0, v0 = _perturbed(sc, T_true, disps)
    b0 = torch.cat((0.005 * torch.ones(6, 3, **F64), 0.05 * torch.ones(6, 3, **F64)), 1)
    state0 = InertialState(v0, b0, torch.eye(3, **F64), torch.zeros((), **F64))
    fixed = torch.zeros(6, dtype=torch.bool)
    fixed[0] = True   # one pose: with gravity known and metric IMU, the rest (incl. scale) is observable
    res = bundle_adjust(T0, d0, edges, coords, INTR, fixed, BAConfig(iterations=30, huber_delta=1e6),
                        extra=terms, extra_state=state0)
    pos_err = (se3_inverse(res.poses)[:, :3, 3] - sc.T_wc[:, :3, 3]).norm(dim=-1).max()
    assert pos_err < 1e-4
    assert (res.extra_state.velocities - sc.velocities).norm(dim=-1).max() < 1e-3
    assert res.extra_state.biases.abs().max() < 2e-3
    seen = torch.zeros_like(disps).index_add_(0, edges.ii, edges.weight) > 0   # pixels with correspondences
    assert (res.disps - disps)[seen].abs().max() < 1e-4
    assert res.costs[-1] < 1e-2 * res.costs[0]


def test_imu_pulls_textureless_keyframes_to_the_truth():
    """Keyframes 3 and 4 see no texture (zero-confidence correspondences): vision alone cannot move them from
    a wrong initial pose; the inertial terms bring them to the truth."""
    sc = make_scenario(n=7, spacing_s=0.25, seed=4)
    T_true = se3_inverse(sc.T_wc)
    disps, coords, edges = visual_problem(T_true)
    blind = torch.isin(edges.ii, torch.tensor([3, 4])) | torch.isin(edges.jj, torch.tensor([3, 4]))
    edges = EdgeSet(edges.ii, edges.jj, edges.target, edges.weight * (~blind)[:, None])
    T0 = T_true.clone()
    T0[3:5] = se3_exp(torch.tensor([0.15, -0.1, 0.05, 0.03, 0.02, -0.04], **F64)) @ T_true[3:5]
    fixed = torch.zeros(7, dtype=torch.bool)
    fixed[:2] = True
    cfg = BAConfig(iterations=20, huber_delta=1e6)
    vis = bundle_adjust(T0, disps.clone(), edges, coords, INTR, fixed, cfg)
    err_vis = (se3_inverse(vis.poses)[3:5, :3, 3] - sc.T_wc[3:5, :3, 3]).norm(dim=-1).max()
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    state0 = InertialState(sc.velocities.clone(), torch.zeros(7, 6, **F64), torch.eye(3, **F64), torch.zeros((), **F64))
    vi = bundle_adjust(T0, disps.clone(), edges, coords, INTR, fixed, cfg, extra=InertialTerms(pre, T_CB),
                       extra_state=state0)
    err_vi = (se3_inverse(vi.poses)[3:5, :3, 3] - sc.T_wc[3:5, :3, 3]).norm(dim=-1).max()
    assert err_vis > 0.1
    assert err_vi < 1e-3


def test_imu_fixes_translation_under_pure_rotation():
    """The camera only rotates about its centre, so the visual terms are blind to translation once the
    disparities may shrink; the inertial terms keep the keyframes at the (unmoved) truth."""
    from vigs_core.sim.trajectory import ProceduralConfig
    cfg = ProceduralConfig(duration_s=6.0, amplitude_xy=0.0, amplitude_z=0.0, yaw_amplitude=0.6,
                           tilt_amplitude=0.1, min_period_s=3.0, max_period_s=6.0)
    sc = make_scenario(n=6, spacing_s=0.25, seed=7, config=cfg)
    T_true = se3_inverse(sc.T_wc)
    disps, coords, edges = visual_problem(T_true, depth=(3.0, 6.0))
    g = torch.Generator().manual_seed(2)
    xi = torch.cat((0.1 * torch.randn(6, 3, generator=g, **F64), torch.zeros(6, 3, **F64)), 1)
    xi[0] = 0
    T0 = se3_exp(xi) @ T_true
    fixed = torch.zeros(6, dtype=torch.bool)
    fixed[0] = True
    cfg_ba = BAConfig(iterations=25, huber_delta=1e6)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    state0 = InertialState(torch.zeros(6, 3, **F64), torch.zeros(6, 6, **F64), torch.eye(3, **F64),
                           torch.zeros((), **F64))
    vis = bundle_adjust(T0, disps.clone(), edges, coords, INTR, fixed, cfg_ba)
    vi = bundle_adjust(T0, disps.clone(), edges, coords, INTR, fixed, cfg_ba, extra=InertialTerms(pre, T_CB),
                       extra_state=state0)
    err = lambda T: float((se3_inverse(T)[:, :3, 3] - sc.T_wc[:, :3, 3]).norm(dim=-1).max())  # noqa: E731
    assert err(vi.poses) < 1e-3
    assert err(vi.poses) < 0.1 * err(vis.poses)


def test_held_depth_keeps_the_window_scale_when_one_interval_contradicts_the_imu():
    """The metric VI odometry's window (one fixed keyframe with anchored velocity and bias) where the images of
    one interval disagree with the IMU (a ground-truth position jump the IMU never felt; here the IMU's position
    delta of interval 2 is off by 10 cm instead). With every disparity free, vision is blind to scale and the
    cheapest explanation rescales the whole window; holding the fixed keyframe's depth
    (``VioConfig.metric_hold_fixed_disparity``) keeps the scale and confines the error."""
    sc = make_scenario(n=6, spacing_s=0.3, seed=2)
    T_true = se3_inverse(sc.T_wc)
    disps, coords, edges = visual_problem(T_true)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    step = pre.delta_p[2] / pre.delta_p[2].norm()
    pre.delta_p[2] = pre.delta_p[2] - 0.1 * step
    fixed = torch.zeros(6, dtype=torch.bool)
    fixed[0] = True
    biases = torch.zeros(6, 6, **F64)
    anchor_std = torch.tensor([1e-3] * 3 + [1e-2] * 3, **F64)
    anchor = AnchorPrior(fixed, sc.velocities.clone(), biases.clone(), 0.01, anchor_std)
    terms = InertialTerms(pre, T_CB, weight=0.03, anchor=anchor)
    state0 = InertialState(sc.velocities.clone(), biases, torch.eye(3, **F64), torch.zeros((), **F64))
    p_true = sc.T_wc[:, :3, 3]

    def scale(res):   # of the window seen from the fixed keyframe
        p = se3_inverse(res.poses)[:, :3, 3]
        return float((p[1:] - p[0]).norm(dim=-1).sum() / (p_true[1:] - p_true[0]).norm(dim=-1).sum())

    cfg = BAConfig(iterations=30, huber_delta=2.0)
    free = bundle_adjust(T_true.clone(), disps.clone(), edges, coords, INTR, fixed, cfg, extra=terms,
                         extra_state=state0)
    held = bundle_adjust(T_true.clone(), disps.clone(), edges, coords, INTR, fixed, cfg, extra=terms,
                         extra_state=state0, fixed_disparity=fixed)
    assert abs(scale(free) - 1.0) > 0.05                              # measured 8.6%
    assert abs(scale(held) - 1.0) < 0.3 * abs(scale(free) - 1.0)      # measured 2.2%


def test_an_interval_of_weight_zero_contributes_nothing():
    """An interval across an IMU gap (``interval_weight`` 0): whatever its preintegration holds, the normal
    equations are those of the other intervals alone (here: interval 1 of 3 corrupted by 1 m and 1 rad)."""
    sc = make_scenario(n=4)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    v, b, _, _ = _random_state(4, True, seed=2)
    state = InertialState(v, b, torch.eye(3, **F64), torch.zeros((), **F64))
    poses = se3_inverse(sc.T_wc)
    weight = torch.tensor([1.0, 0.0, 1.0], **F64)
    H, g, cost = InertialTerms(pre, T_CB, interval_weight=weight).linearize(poses, state)
    pre.delta_p[1] += 1.0
    pre.delta_R[1] = so3_exp(torch.tensor([1.0, 0.0, 0.0], **F64)) @ pre.delta_R[1]
    H2, g2, cost2 = InertialTerms(pre, T_CB, interval_weight=weight).linearize(poses, state)
    assert torch.allclose(H, H2) and torch.allclose(g, g2) and math.isclose(float(cost), float(cost2))
    H3, _, cost3 = InertialTerms(pre, T_CB).linearize(poses, state)   # with its weight, the corruption counts
    assert float(cost3) > 10 * float(cost) and not torch.allclose(H, H3)
