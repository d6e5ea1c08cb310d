"""Dense BA on exact synthetic problems: Jacobians, exact recovery, noise, outliers, Schur, extra terms."""
import math

import pytest
import torch

from vigs_core.geometry import se3_exp, se3_inverse
from vigs_core.solver import (BAConfig, EdgeSet, Intrinsics, align_pose, bundle_adjust, huber_weight,
                              linearize_visual, reproject, schur_reduce, visual_cost)

torch.set_num_threads(1)
INTR = Intrinsics(180.0, 180.0, 94.5, 59.5)


def make_problem(n=4, grid=(12, 8), seed=0, dtype=torch.float64):
    """Keyframes on a short arc looking at a textured slanted wall: true poses, disparities, exact edges."""
    g = torch.Generator().manual_seed(seed)
    us = torch.linspace(8, 180, grid[0], dtype=dtype)
    vs = torch.linspace(6, 112, grid[1], dtype=dtype)
    coords = torch.stack(torch.meshgrid(us, vs, indexing="xy"), -1).reshape(-1, 2)
    poses = []
    for k in range(n):
        xi = torch.tensor([0.12 * k, 0.03 * k, 0.02 * math.sin(k), 0.01 * k, -0.03 * k, 0.005 * k], dtype=dtype)
        poses.append(se3_exp(xi))
    poses = torch.stack(poses)
    depth = 2.0 + 1.5 * torch.rand(n, coords.shape[0], generator=g, dtype=dtype)
    disps = 1.0 / depth
    ii, jj = zip(*[(i, j) for i in range(n) for j in range(n) if i != j])
    ii, jj = torch.tensor(ii), torch.tensor(jj)
    proj = reproject(poses[ii], poses[jj], disps[ii], coords, INTR)
    w = proj.valid.to(dtype)
    return poses, disps, coords, EdgeSet(ii, jj, proj.uv, w)


def perturb(poses, disps, scale=1.0, seed=1):
    g = torch.Generator().manual_seed(seed)
    n = poses.shape[0]
    xi = scale * torch.cat((0.02 * torch.randn(n, 3, generator=g), 0.01 * torch.randn(n, 3, generator=g)), 1)
    xi = xi.to(poses.dtype)
    xi[:2] = 0
    d = disps * (1 + 0.1 * scale * torch.randn(disps.shape, generator=g, dtype=disps.dtype))
    return se3_exp(xi) @ poses, d


def test_jacobians_match_finite_differences():
    poses, disps, coords, edges = make_problem(n=2, grid=(4, 3))
    Ti, Tj, d = poses[:1], poses[1:2], disps[:1]
    proj = reproject(Ti, Tj, d, coords, INTR, jacobians=True)
    eps = 1e-6
    for k in range(6):
        dx = torch.zeros(6, dtype=torch.float64)
        dx[k] = eps
        up = reproject(se3_exp(dx) @ Ti, Tj, d, coords, INTR).uv
        um = reproject(se3_exp(-dx) @ Ti, Tj, d, coords, INTR).uv
        assert torch.allclose((up - um) / (2 * eps), proj.J_i[..., k], atol=1e-5)
        up = reproject(Ti, se3_exp(dx) @ Tj, d, coords, INTR).uv
        um = reproject(Ti, se3_exp(-dx) @ Tj, d, coords, INTR).uv
        assert torch.allclose((up - um) / (2 * eps), proj.J_j[..., k], atol=1e-5)
    up = reproject(Ti, Tj, d + eps, coords, INTR).uv
    um = reproject(Ti, Tj, d - eps, coords, INTR).uv
    assert torch.allclose((up - um) / (2 * eps), proj.J_d, atol=1e-5)


def test_schur_complement_matches_dense_elimination():
    poses, disps, coords, edges = make_problem(n=3, grid=(5, 4))
    poses, disps = perturb(poses, disps)
    sys_ = linearize_visual(poses, disps, edges, coords, INTR, huber_delta=1e9)
    n, P = disps.shape
    C = sys_.C + 1e-3
    S, s = schur_reduce(sys_, C)
    # dense E (6n, nP) from the blocks
    E = torch.zeros(n, 6, n, P, dtype=torch.float64)
    for a, src in enumerate(sys_.src.tolist()):
        for k, pose in enumerate(sys_.block_pose[a].tolist()):
            if pose >= 0:
                E[pose, :, src] += sys_.block_E[a, k]
    E = E.reshape(6 * n, n * P)
    B = sys_.B.permute(0, 2, 1, 3).reshape(6 * n, 6 * n)
    S_ref = B - E @ torch.diag(1 / C.reshape(-1)) @ E.T
    s_ref = sys_.v.reshape(-1) - E @ (sys_.w / C).reshape(-1)
    assert torch.allclose(S, S_ref, atol=1e-8 * S_ref.abs().max())
    assert torch.allclose(s, s_ref, atol=1e-8 * s_ref.abs().max())


@pytest.mark.parametrize("compiled", [False, True])
def test_normal_equations_match_per_pixel_source_jacobians(compiled):
    """linearize_visual forms the source-pose blocks from J_i = -J_j Ad; compare with the per-pixel J_i (tensor
    terms, and the compiled kernel where numba is installed)."""
    poses, disps, coords, edges = make_problem(n=3, grid=(6, 5))
    poses, disps = perturb(poses, disps)
    sys_ = linearize_visual(poses, disps, edges, coords, INTR, huber_delta=1e9, compiled=compiled)
    proj = reproject(poses[edges.ii], poses[edges.jj], disps[edges.ii], coords, INTR, jacobians=True)
    r = edges.target - proj.uv
    W = edges.pixel_weight() * proj.valid[..., None]
    n, P = disps.shape
    B = torch.zeros(n, n, 6, 6, dtype=torch.float64)
    v = torch.zeros(n, 6, dtype=torch.float64)
    E_src = torch.zeros(n, P, 6, dtype=torch.float64)    # the source's own E block
    for e, (i, j) in enumerate(zip(edges.ii.tolist(), edges.jj.tolist())):
        J = {i: proj.J_i[e].reshape(-1, 6), j: proj.J_j[e].reshape(-1, 6)}
        w = W[e].reshape(-1)
        for a in (i, j):
            v[a] += J[a].T @ (w * r[e].reshape(-1))
            for b in (i, j):
                B[a, b] += J[a].T @ (w[:, None] * J[b])
        E_src[i] += (W[e] * proj.J_d[e])[..., None].mul(proj.J_i[e]).sum(1)
    assert torch.allclose(sys_.B, B, atol=1e-9 * B.abs().max())
    assert torch.allclose(sys_.v, v, atol=1e-9 * v.abs().max())
    own = sys_.block_E[:, 0].transpose(1, 2)                      # block 0 of each source is its own pose
    assert torch.allclose(own, E_src[sys_.src], atol=1e-9 * E_src.abs().max())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_linearisation_equals_the_tensor_one(dtype):
    """The numba kernel (:mod:`vigs_core.solver.linearize_numba`) gives the tensor version's system: pixels
    projected behind the depth limit (invalid), Huber-weighted outliers, per-axis confidences, sources with several
    outgoing edges. Float64 to rounding, float32 to its precision (the kernel sums in float64)."""
    pytest.importorskip("numba")
    poses, disps, coords, edges = make_problem(n=4, grid=(16, 10), dtype=dtype)
    poses, disps = perturb(poses, disps)
    poses[3] = torch.tensor([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.6], [0, 0, 0, 1]], dtype=dtype) @ poses[3]
    g = torch.Generator().manual_seed(7)
    target = edges.target + 4.0 * torch.randn(edges.target.shape, generator=g, dtype=dtype)
    conf = torch.rand(edges.target.shape, generator=g, dtype=dtype)
    edges = EdgeSet(edges.ii, edges.jj, target, conf)
    ref = linearize_visual(poses, disps, edges, coords, INTR, huber_delta=2.0, compiled=False)
    out = linearize_visual(poses, disps, edges, coords, INTR, huber_delta=2.0, compiled=True)
    assert 0.05 < float((~ref.valid).float().mean()) < 0.5                # some pixels behind the depth limit
    rn = ref.residual.norm(dim=-1)[ref.valid]
    assert float((rn > 2.0).float().mean()) > 0.3                          # the Huber weight is active
    assert torch.equal(out.valid, ref.valid) and torch.equal(out.block_pose, ref.block_pose)
    assert ref.block_E.shape[1] == 4                                        # own block + 3 targets per source
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    for name in ("B", "v", "C", "w", "block_E", "residual", "cost"):
        a, b = getattr(ref, name), getattr(out, name)
        assert a.dtype == b.dtype == dtype, name
        assert float((a - b).abs().max()) <= tol * float(a.abs().max()), name
    cost = visual_cost(poses, disps, edges, coords, INTR, 2.0, compiled=True)     # the LM trials' cost alone
    assert cost.dtype == dtype and abs(float(cost) - float(ref.cost)) <= tol * float(ref.cost)
    assert abs(float(visual_cost(poses, disps, edges, coords, INTR, 2.0, compiled=False)) - float(ref.cost)) <= (
        tol * float(ref.cost))


def test_float32_visual_terms_reach_the_float64_solution():
    poses, disps, coords, edges = make_problem(grid=(16, 10))
    g = torch.Generator().manual_seed(3)
    noisy = EdgeSet(edges.ii, edges.jj, edges.target + 0.5 * torch.randn(edges.target.shape, generator=g,
                                                                       dtype=torch.float64), edges.weight)
    p0, d0 = perturb(poses, disps)
    fixed = torch.tensor([True, True, False, False])
    ref = bundle_adjust(p0, d0, noisy, coords, INTR, fixed, BAConfig(iterations=20))
    f32 = bundle_adjust(p0, d0, noisy, coords, INTR, fixed, BAConfig(iterations=20), visual_dtype=torch.float32)
    assert f32.poses.dtype == torch.float64 and f32.disps.dtype == torch.float64
    assert (f32.poses - ref.poses).abs().max() < 1e-5
    assert ((f32.disps - ref.disps).abs() / ref.disps).max() < 1e-4
    assert f32.costs[-1] < 1.0001 * ref.costs[-1] and f32.costs[-1] < 0.05 * f32.costs[0]


def test_exact_problem_converges_to_machine_precision():
    poses, disps, coords, edges = make_problem()
    p0, d0 = perturb(poses, disps)
    fixed = torch.tensor([True, True, False, False])
    res = bundle_adjust(p0, d0, edges, coords, INTR, fixed, BAConfig(iterations=30))
    assert res.costs[-1] < 1e-20
    assert (res.poses - poses).abs().max() < 1e-10
    assert (res.disps - disps).abs().max() < 1e-10
    assert res.costs[0] > 1.0


def test_noise_gives_bounded_error():
    poses, disps, coords, edges = make_problem(grid=(16, 10))
    g = torch.Generator().manual_seed(3)
    sigma = 0.5
    noisy = EdgeSet(edges.ii, edges.jj, edges.target + sigma * torch.randn(edges.target.shape, generator=g,
                                                                         dtype=torch.float64), edges.weight)
    p0, d0 = perturb(poses, disps)
    fixed = torch.tensor([True, True, False, False])
    res = bundle_adjust(p0, d0, noisy, coords, INTR, fixed, BAConfig(iterations=20))
    t_err = (se3_inverse(res.poses)[:, :3, 3] - se3_inverse(poses)[:, :3, 3]).norm(dim=-1).max()
    assert t_err < 0.01  # metres, 1 cm at 2-3.5 m depth with 0.5 px noise
    assert ((res.disps - disps).abs() / disps).median() < 0.02
    r = (noisy.target - reproject(res.poses[edges.ii], res.poses[edges.jj], res.disps[edges.ii], coords,
                                  INTR).uv).norm(dim=-1)
    assert 0.3 < float(r.pow(2).mean().sqrt()) < 0.8  # residual RMS close to sigma*sqrt(2)


def test_outliers_are_down_weighted():
    poses, disps, coords, edges = make_problem(grid=(16, 10))
    g = torch.Generator().manual_seed(5)
    target = edges.target.clone()
    bad = torch.rand(target.shape[:2], generator=g) < 0.15
    target[bad] += 25.0 * torch.randn(int(bad.sum()), 2, generator=g, dtype=torch.float64)
    corrupt = EdgeSet(edges.ii, edges.jj, target, edges.weight)
    fixed = torch.tensor([True, True, False, False])
    p0, d0 = perturb(poses, disps)
    robust = bundle_adjust(p0, d0, corrupt, coords, INTR, fixed, BAConfig(iterations=25, huber_delta=1.0))
    plain = bundle_adjust(p0, d0, corrupt, coords, INTR, fixed, BAConfig(iterations=25, huber_delta=1e6))
    err = lambda p: (se3_inverse(p)[:, :3, 3] - se3_inverse(poses)[:, :3, 3]).norm(dim=-1).max()
    assert err(robust.poses) < 0.03
    assert err(robust.poses) < 0.2 * err(plain.poses)
    # the outliers end with small IRLS weights, the inliers with full weight
    r = (target - reproject(robust.poses[edges.ii], robust.poses[edges.jj], robust.disps[edges.ii], coords,
                            INTR).uv).norm(dim=-1)
    w = huber_weight(r, 1.0)
    assert float(w[bad].mean()) < 0.15
    assert float(w[~bad].mean()) > 0.9


def test_single_fixed_pose_monocular_gauge_converges_up_to_scale():
    poses, disps, coords, edges = make_problem()
    p0, d0 = perturb(poses, disps)
    fixed = torch.tensor([True, False, False, False])
    res = bundle_adjust(p0, d0, edges, coords, INTR, fixed, BAConfig(iterations=40))
    assert res.costs[-1] < 1e-12
    c_est = se3_inverse(res.poses)[:, :3, 3]
    c_true = se3_inverse(poses)[:, :3, 3]
    scale = float((c_est[1:] * c_true[1:]).sum() / (c_est[1:] ** 2).sum())
    assert torch.allclose(c_est * scale, c_true, atol=1e-6)
    assert torch.allclose(res.disps / scale, disps, atol=1e-6)


class PosePrior:
    """Extra term: prior ``|Log(T_k T_ref^-1)|^2`` on one pose, with one dummy extra state ``x`` pulled to 1."""

    dim = 1

    def __init__(self, k, T_ref, weight):
        self.k, self.T_ref, self.weight = k, T_ref, weight

    def _res(self, poses):
        from vigs_core.geometry import se3_log
        return se3_log(poses[self.k] @ se3_inverse(self.T_ref))

    def cost(self, poses, state):
        return 0.5 * self.weight * (self._res(poses) ** 2).sum() + 0.5 * (state - 1.0) ** 2

    def linearize(self, poses, state):
        n = poses.shape[0]
        H = torch.zeros(6 * n + 1, 6 * n + 1, dtype=poses.dtype)
        g = torch.zeros(6 * n + 1, dtype=poses.dtype)
        sl = slice(6 * self.k, 6 * self.k + 6)
        H[sl, sl] = self.weight * torch.eye(6, dtype=poses.dtype)  # small-residual approximation J = I
        g[sl] = -self.weight * self._res(poses)
        H[-1, -1] = 1.0
        g[-1] = 1.0 - state
        return H, g, self.cost(poses, state)

    def retract(self, state, delta):
        return state + delta[0]


def test_additional_terms_enter_the_same_normal_equations():
    poses, disps, coords, edges = make_problem()
    p0, d0 = perturb(poses, disps)
    # only pose 0 fixed: scale is free, and the prior on pose 3 at the truth pins it
    fixed = torch.tensor([True, False, False, False])
    prior = PosePrior(3, poses[3], weight=1e4)
    res = bundle_adjust(p0, d0, edges, coords, INTR, fixed, BAConfig(iterations=40), extra=prior,
                        extra_state=torch.tensor(0.0, dtype=torch.float64))
    assert abs(float(res.extra_state) - 1.0) < 1e-9
    assert (res.poses - poses).abs().max() < 1e-7
    assert res.costs[-1] < 1e-14


def test_align_pose_recovers_frame_pose():
    poses, disps, coords, edges = make_problem(n=2, grid=(16, 10))
    target = reproject(poses[:1], poses[1:], disps[:1], coords, INTR).uv[0]
    T0 = se3_exp(torch.tensor([0.03, -0.02, 0.02, 0.01, 0.02, -0.01], dtype=torch.float64)) @ poses[1]
    out = align_pose(poses[0], disps[0], coords, INTR, target, torch.ones(coords.shape[0], dtype=torch.float64),
                     T0, iterations=10)
    assert (out.pose - poses[1]).abs().max() < 1e-9
    assert out.rms < 1e-8 and out.inlier_ratio == pytest.approx(1.0)


def test_align_pose_float32_projections_and_outliers():
    """float32 disparities/targets (tracking's type): exact targets give the float64 pose back within float32
    resolution; with 20 % gross outliers the Huber weights keep the error several times below plain least
    squares, and the outliers are counted out of the inlier ratio."""
    poses, disps, coords, edges = make_problem(n=2, grid=(24, 16))
    target = reproject(poses[:1], poses[1:], disps[:1], coords, INTR).uv[0]
    T0 = se3_exp(torch.tensor([0.02, -0.01, 0.02, 0.01, 0.01, -0.01], dtype=torch.float64)) @ poses[1]
    f32 = torch.float32
    ones = torch.ones(coords.shape[0], dtype=f32)
    out = align_pose(poses[0], disps[0].to(f32), coords.to(f32), INTR, target.to(f32), ones, T0, iterations=10)
    assert out.pose.dtype == torch.float64
    assert (out.pose - poses[1]).abs().max() < 1e-4

    g = torch.Generator().manual_seed(3)
    bad = torch.rand(coords.shape[0], generator=g) < 0.2
    noisy = target + bad[:, None] * 20.0 * torch.randn(coords.shape, generator=g, dtype=torch.float64)
    robust = align_pose(poses[0], disps[0].to(f32), coords.to(f32), INTR, noisy.to(f32), ones, T0, 15, 2.0)
    plain = align_pose(poses[0], disps[0].to(f32), coords.to(f32), INTR, noisy.to(f32), ones, T0, 15, 1e6)
    err_robust = float((robust.pose - poses[1]).abs().max())
    assert err_robust < 0.2 * float((plain.pose - poses[1]).abs().max())
    assert robust.inlier_ratio == pytest.approx(1.0 - float(bad.double().mean()), abs=0.02)


def test_align_pose_stops_on_a_singular_system():
    """No usable correspondence (all weights zero): the initial pose is returned unchanged, with no inliers."""
    poses, disps, coords, edges = make_problem(n=2)
    target = reproject(poses[:1], poses[1:], disps[:1], coords, INTR).uv[0]
    out = align_pose(poses[0], disps[0], coords, INTR, target, torch.zeros(coords.shape[0], dtype=torch.float64),
                     poses[0], iterations=5)
    assert torch.equal(out.pose, poses[0])
    assert out.inlier_ratio == 0.0 and out.rms == float("inf")


def test_fixed_keyframe_disparities_pin_the_scale():
    poses, disps, coords, edges = make_problem()
    p0, d0 = perturb(poses, disps)
    d0[0] = disps[0]
    fixed = torch.tensor([True, False, False, False])
    frozen = torch.tensor([True, False, False, False])
    res = bundle_adjust(p0, d0, edges, coords, INTR, fixed, BAConfig(iterations=40), fixed_disparity=frozen)
    assert torch.equal(res.disps[0], disps[0])
    assert (res.poses - poses).abs().max() < 1e-9
    assert (res.disps - disps).abs().max() < 1e-9
