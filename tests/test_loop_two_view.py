"""Relative Sim(3) from dense correspondences with depth: recovery on rendered views, exact Jacobians, rejection of
unrelated views."""
import math

import numpy as np
import torch

from loop_synthetic import cast, look, render, room
from vigs_core.frontend import DISFlowEstimator, PixelGrid
from vigs_core.geometry import sim3_exp, sim3_from_srt, sim3_log, so3_exp
from vigs_core.loop.two_view import (TwoViewCorrespondences, estimate_relative_sim3, grid_points,
                                     two_view_residuals)
from vigs_core.solver import Intrinsics

D = torch.float64
W, H = 160, 120
INTR = Intrinsics(100.0, 100.0, 79.5, 59.5)
GRID = PixelGrid(W, H, 8)


def view(yaw_deg, position):
    T = look(math.radians(yaw_deg), np.asarray(position, dtype=float))
    depth = cast(room(), T, GRID.coords(), INTR, shade=False)[0]
    return T, render(room(), T, INTR, W, H), torch.from_numpy(depth)


def correspondences(est, src, dst):
    c = est.estimate(src, dst)
    return TwoViewCorrespondences(torch.from_numpy(c.target), torch.from_numpy(c.weight.astype(np.float64)))


def test_recovers_relative_similarity_including_scale():
    torch.set_num_threads(1)
    Ta, ia, za = view(30.0, [0.3, 0.2, 1.5])
    Tb, ib, zb = view(37.0, [0.45, 0.1, 1.45])
    sa, sb = 0.8, 1.25  # each keyframe's depth units (drifted monocular scales)
    est = DISFlowEstimator(GRID)
    res = estimate_relative_sim3(za * sa, zb * sb, correspondences(est, ia, ib), correspondences(est, ib, ia),
                                 GRID, INTR)
    assert res.accepted, res.reason
    rel = torch.linalg.inv(Ta) @ Tb
    truth = sim3_from_srt(torch.tensor(sa / sb, dtype=D), rel[:3, :3], sa * rel[:3, 3])
    err = sim3_log(torch.linalg.inv(truth) @ res.relative)
    assert math.degrees(float(err[3:6].norm())) < 0.5
    assert abs(float(err[6])) < 0.02                          # relative scale within 2%
    assert float((res.relative[:3, 3] - truth[:3, 3]).norm()) < 0.03
    assert res.inlier_fraction > 0.8 and res.rms_px < 1.0
    assert bool((torch.linalg.eigvalsh(res.information) > 0).all())


def test_rejects_views_of_different_walls():
    _, ia, za = view(0.0, [0.0, 0.0, 1.5])
    _, ib, zb = view(90.0, [0.0, 0.0, 1.5])
    est = DISFlowEstimator(GRID)
    res = estimate_relative_sim3(za, zb, correspondences(est, ia, ib), correspondences(est, ib, ia), GRID, INTR)
    assert not res.accepted
    assert res.reason


def test_residual_jacobians_match_numerical():
    gen = torch.Generator().manual_seed(1)
    P = 20
    pa = torch.rand(P, 3, generator=gen, dtype=D) + torch.tensor([-0.5, -0.5, 2.0], dtype=D)
    pb = torch.rand(P, 3, generator=gen, dtype=D) + torch.tensor([-0.5, -0.5, 2.0], dtype=D)
    Z = sim3_from_srt(torch.tensor(1.3, dtype=D), so3_exp(torch.tensor([0.1, -0.2, 0.05], dtype=D)),
                      torch.tensor([0.2, -0.1, 0.3], dtype=D))
    corr = TwoViewCorrespondences(torch.rand(P, 2, generator=gen, dtype=D) * 100, torch.ones(P, dtype=D),
                                  torch.full((P,), 2.5, dtype=D))
    analytic = two_view_residuals(Z, pa, pb, corr, corr, INTR)
    eps = 1e-6
    for k in range(7):
        d = torch.zeros(7, dtype=D)
        d[k] = eps
        plus = two_view_residuals(sim3_exp(d) @ Z, pa, pb, corr, corr, INTR, jacobians=False)
        minus = two_view_residuals(sim3_exp(-d) @ Z, pa, pb, corr, corr, INTR, jacobians=False)
        for a, p, m in zip(analytic, plus, minus):
            # r = u - pi(.), so d r / d delta = -J_pi(.); r_depth = log z - log z_measured
            num = (p.r - m.r) / (2 * eps)
            np.testing.assert_allclose(num.numpy(), -a.J[:, :, k].numpy(), rtol=1e-5, atol=1e-5)
            num = (p.r_depth - m.r_depth) / (2 * eps)
            np.testing.assert_allclose(num.numpy(), a.J_depth[:, k].numpy(), rtol=1e-5, atol=1e-7)


def test_grid_points_scale_with_depth():
    coords = torch.tensor([[79.5, 59.5], [179.5, 59.5]], dtype=D)
    pts = grid_points(torch.tensor([2.0, 4.0], dtype=D), coords, INTR)
    np.testing.assert_allclose(pts.numpy(), [[0.0, 0.0, 2.0], [4.0, 0.0, 4.0]])
