"""Marginalisation prior of the sliding window: marginalising keyframes out of a small exact problem gives the
remaining states the same Gauss-Newton step as the full problem, and the prior's gradient and Hessian are those
of its cost away from the linearisation point."""
import math

import numpy as np
import pytest
import torch

from vigs_core.geometry import se3_exp, se3_inverse
from vigs_core.imu.preintegration import preintegrate_between
from vigs_core.solver import EdgeSet
from vigs_core.solver.normal_equations import linearize_visual, schur_reduce
from vigs_core.vio.inertial_terms import AnchorPrior, InertialState, InertialTerms, MarginalPrior, state_columns
from vigs_core.vio.marginalization import marginalize_keyframe
from vio_synthetic import INTR, NOISE, T_CB, make_scenario, visual_problem

torch.set_num_threads(1)
F64 = dict(dtype=torch.float64)
BIAS_STD = torch.tensor([0.1] * 3 + [0.5] * 3, **F64)
ANCHOR = (0.01, torch.tensor([1e-3] * 3 + [1e-2] * 3, **F64))
WEIGHT = 0.03


def _problem(n=6, per_keyframe=True, seed=3):
    """Noisy IMU, perturbed states, forward visual edges only (``i < j``: the edges a marginalisation keeps)."""
    sc = make_scenario(n=n, spacing_s=0.3, seed=seed, imu_noise=True)
    T_true = se3_inverse(sc.T_wc)
    disps, coords, edges = visual_problem(T_true)
    fwd = edges.ii < edges.jj
    edges = EdgeSet(edges.ii[fwd], edges.jj[fwd], edges.target[fwd], edges.weight[fwd])
    g = torch.Generator().manual_seed(seed)
    poses = se3_exp(torch.cat((0.02 * torch.randn(n, 3, generator=g, **F64),
                               0.005 * torch.randn(n, 3, generator=g, **F64)), 1)) @ T_true
    disps = disps * (1 + 0.05 * torch.randn(disps.shape, generator=g, **F64))
    vel = sc.velocities + 0.05 * torch.randn(n, 3, generator=g, **F64)
    nb = n if per_keyframe else 1
    biases = torch.cat((0.002 * torch.randn(nb, 3, generator=g, **F64),
                        0.05 * torch.randn(nb, 3, generator=g, **F64)), 1)
    pre = preintegrate_between(sc.imu, sc.stamps_ns, NOISE)
    return sc, poses, disps, coords, edges, vel, biases, pre


def _pre_slice(pre, a, b):
    """Intervals ``a .. b-1`` of a batched preintegration."""
    out = {k: (v[a:b] if isinstance(v, (torch.Tensor, np.ndarray)) else v) for k, v in vars(pre).items()}
    return type(pre)(**out)


def _visual(poses, disps, coords, edges, keep):
    """Reduced camera system (6n, 6n), (6n,) of the edges selected by ``keep`` (E,) bool."""
    sub = EdgeSet(edges.ii[keep], edges.jj[keep], edges.target[keep], edges.weight[keep])
    system = linearize_visual(poses, disps, sub, coords, INTR, 1e6)
    return schur_reduce(system, system.C + 1e-6)


def _solve(H, g, free):
    dx = torch.zeros_like(g)
    dx[free] = torch.linalg.solve(H[free][:, free], g[free])
    return dx


@pytest.mark.parametrize("per_keyframe", [True, False])
def test_marginalising_two_keyframes_keeps_the_gauss_newton_step_of_the_full_problem(per_keyframe):
    n = 6
    sc, poses, disps, coords, edges, vel, biases, pre = _problem(n, per_keyframe)
    kw = dict(estimate_bias=True, per_keyframe_bias=per_keyframe, weight=WEIGHT, bias_prior_std=BIAS_STD)
    state = InertialState(vel, biases, torch.eye(3, **F64), torch.zeros((), **F64))

    # full problem: keyframe 0's pose held (gauge), its velocity and bias anchored
    mask = torch.zeros(n, dtype=torch.bool)
    mask[0] = True
    anchor = AnchorPrior(mask, vel.clone(), biases.expand(n, 6).clone(), ANCHOR[0], ANCHOR[1])
    full = InertialTerms(pre, T_CB, anchor=anchor, **kw)
    H, g, _ = full.linearize(poses, state)
    S, s = _visual(poses, disps, coords, edges, torch.ones_like(edges.ii, dtype=torch.bool))
    H[:6 * n, :6 * n] += S
    g[:6 * n] += s
    free = torch.ones(H.shape[0], dtype=torch.bool)
    free[:6] = False
    dx_full = _solve(H, g, free)

    # marginalise keyframe 0 (first: conditioned pose, anchor), then keyframe 1 out of the window
    mkw = dict(estimate_bias=True, per_keyframe_bias=per_keyframe, gravity=9.81, weight=WEIGHT,
               bias_prior_std=BIAS_STD)
    bsel = (lambda a: biases[a:]) if per_keyframe else (lambda a: biases)
    prior = None
    for k in (0, 1):
        vis = _visual(poses[k:], disps[k:], coords, EdgeSet(edges.ii - k, edges.jj - k, edges.target, edges.weight),
                      (edges.ii == k))
        prior = marginalize_keyframe(prior, list(range(k, n)), poses[k:], vel[k:], bsel(k), _pre_slice(pre, k, k + 1),
                                     T_CB, visual=vis, anchor_std=ANCHOR, **mkw)
    assert prior.ids == [2, 3, 4, 5]

    # the window 2..5: its inertial factors, its own bias priors, its hosted edges and the prior
    win = InertialTerms(_pre_slice(pre, 2, n - 1), T_CB, marginal=prior, marginal_index=[0, 1, 2, 3], **kw)
    st2 = InertialState(vel[2:], bsel(2), torch.eye(3, **F64), torch.zeros((), **F64))
    H2, g2, _ = win.linearize(poses[2:], st2)
    S2, s2 = _visual(poses[2:], disps[2:], coords, EdgeSet(edges.ii - 2, edges.jj - 2, edges.target, edges.weight),
                     edges.ii >= 2)
    H2[:24, :24] += S2
    g2[:24] += s2
    dx_win = torch.linalg.solve(H2, g2)      # no keyframe held: the prior carries the gauge

    cols = state_columns([2, 3, 4, 5], n, True, per_keyframe)
    assert torch.allclose(dx_win, dx_full[cols], rtol=1e-6, atol=1e-9 * float(dx_full.abs().max()))
    assert float(dx_full[cols].abs().max()) > 1e-3   # a real step, not a trivial zero


def test_marginal_prior_gradient_and_hessian_match_its_cost_away_from_the_linearisation_point():
    n = 4
    sc, poses, _, _, _, vel, biases, pre = _problem(n, True, seed=5)
    g = torch.Generator().manual_seed(1)
    K = 2
    D = 15 * K
    L = torch.randn(D, D, generator=g, **F64)
    lin = se3_exp(0.05 * torch.randn(K, 6, generator=g, **F64)) @ poses[1:3]
    prior = MarginalPrior([1, 2], lin, vel[1:3] + 0.1, biases[1:3] + 0.01, L @ L.T + torch.eye(D, **F64),
                          torch.randn(D, generator=g, **F64), 0.0)
    terms = InertialTerms(pre, T_CB, marginal=prior, marginal_index=[1, 2])
    state = InertialState(vel, biases, torch.eye(3, **F64), torch.zeros((), **F64))
    H, grad, cost = terms.linearize(poses, state)
    assert math.isclose(float(cost), float(terms.cost(poses, state)), rel_tol=1e-12)
    assert torch.allclose(H, H.T)
    step = 1e-7 * grad / grad.norm()
    p1 = se3_exp(step[:6 * n].view(n, 6)) @ poses
    s1 = terms.retract(state, step[6 * n:])
    assert float(cost - terms.cost(p1, s1)) == pytest.approx(float(grad @ step), rel=1e-4)


def test_marginal_prior_with_the_wrong_layout_is_rejected():
    _, poses, _, _, _, vel, biases, pre = _problem(4, True)
    prior = MarginalPrior([1, 2], poses[1:3], vel[1:3], biases[1:3], torch.eye(30, **F64), torch.zeros(30, **F64),
                          0.0)
    InertialTerms(pre, T_CB, marginal=prior, marginal_index=[1, 2])
    with pytest.raises(ValueError, match="MarginalPrior"):   # per-keyframe biases, terms with one global bias
        InertialTerms(pre, T_CB, per_keyframe_bias=False, marginal=prior, marginal_index=[1, 2])
    with pytest.raises(ValueError, match="window positions"):
        InertialTerms(pre, T_CB, marginal=prior, marginal_index=[1, 7])
