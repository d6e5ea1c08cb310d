"""Geometry: SO(3)/SE(3)/Sim(3) maps and Jacobians against scipy and numerical differentiation."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vigs_core import geometry as g
from vigs_core.geometry import se3, sim3

D = torch.float64


def random_rotvecs(n, seed=0, max_angle=np.pi):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return torch.from_numpy(axis * rng.uniform(0, max_angle, size=(n, 1)))


def edge_rotvecs():
    """Zero, tiny, the Taylor switch-over, and within 1e-9 of pi about several axes."""
    axes = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [-1, 2, 0.5]], dtype=D)
    axes = axes / axes.norm(dim=1, keepdim=True)
    angles = torch.tensor([0.0, 1e-12, 1e-8, 9.9e-5, 1.01e-4, 1e-2, np.pi - 1e-9, np.pi - 1e-6, np.pi], dtype=D)
    return (axes[:, None, :] * angles[None, :, None]).reshape(-1, 3)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_hat_is_the_cross_product_matrix(dtype):
    v, w = torch.randn(4, 5, 3, dtype=dtype), torch.randn(4, 5, 3, dtype=dtype)
    K = g.hat(v)
    assert K.shape == (4, 5, 3, 3) and K.dtype == dtype
    assert torch.equal(K, -K.transpose(-1, -2))
    torch.testing.assert_close((K @ w[..., None])[..., 0], torch.linalg.cross(v, w))
    assert torch.equal(g.vee(K), v)
    assert g.hat(v[0, 0]).shape == (3, 3)


def test_so3_exp_matches_scipy():
    phi = torch.cat((random_rotvecs(200), edge_rotvecs()))
    ref = Rotation.from_rotvec(phi.numpy()).as_matrix()
    np.testing.assert_allclose(g.so3_exp(phi).numpy(), ref, atol=1e-14)


def test_so3_log_inverts_exp_including_near_pi():
    phi = torch.cat((random_rotvecs(200, max_angle=np.pi - 1e-3), edge_rotvecs()))
    back = g.so3_log(g.so3_exp(phi))
    # Near pi, phi and -phi name the same rotation: compare the rotations, and the angle.
    np.testing.assert_allclose(g.so3_exp(back).numpy(), g.so3_exp(phi).numpy(), atol=1e-12)
    np.testing.assert_allclose(back.norm(dim=1).numpy(), phi.norm(dim=1).numpy(), atol=1e-9)
    away = phi.norm(dim=1) < np.pi - 1e-3
    np.testing.assert_allclose(back[away].numpy(), phi[away].numpy(), atol=1e-12)


def test_quaternion_conventions_match_scipy():
    rot = Rotation.random(100, random_state=3)
    q_xyzw = torch.from_numpy(rot.as_quat())  # scipy: scalar last
    q_wxyz = g.quat_xyzw_to_wxyz(q_xyzw)
    np.testing.assert_allclose(g.quat_to_matrix(q_wxyz).numpy(), rot.as_matrix(), atol=1e-14)
    back = g.matrix_to_quat(torch.from_numpy(rot.as_matrix()))
    assert (back[:, 0] >= 0).all()
    same = torch.minimum((back - q_wxyz).abs().amax(1), (back + q_wxyz).abs().amax(1))
    assert same.max() < 1e-14
    np.testing.assert_allclose(g.quat_wxyz_to_xyzw(q_wxyz).numpy(), q_xyzw.numpy())
    # Hamilton product composes like matrices.
    q1, q2 = q_wxyz[:50], q_wxyz[50:]
    np.testing.assert_allclose(
        g.quat_to_matrix(g.quat_multiply(q1, q2)).numpy(),
        (g.quat_to_matrix(q1) @ g.quat_to_matrix(q2)).numpy(),
        atol=1e-14,
    )


def numeric_jacobian(f, x, eps=1e-6):
    cols = []
    for k in range(x.shape[-1]):
        d = torch.zeros_like(x)
        d[..., k] = eps
        cols.append((f(x + d) - f(x - d)) / (2 * eps))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("max_angle", [1e-6, 0.5, 3.0])
def test_so3_jacobians_numerically(max_angle):
    phi = random_rotvecs(20, seed=1, max_angle=max_angle)
    r0 = g.so3_exp(phi)
    # Right: Log(Exp(phi)^T Exp(phi + d)) = J_r d.
    jr = numeric_jacobian(lambda p: g.so3_log(r0.transpose(-1, -2) @ g.so3_exp(p)), phi)
    jl = numeric_jacobian(lambda p: g.so3_log(g.so3_exp(p) @ r0.transpose(-1, -2)), phi)
    np.testing.assert_allclose(g.so3_right_jacobian(phi).numpy(), jr.numpy(), atol=1e-8)
    np.testing.assert_allclose(g.so3_left_jacobian(phi).numpy(), jl.numpy(), atol=1e-8)
    eye = np.broadcast_to(np.eye(3), (20, 3, 3))
    np.testing.assert_allclose((g.so3_right_jacobian_inv(phi) @ g.so3_right_jacobian(phi)).numpy(), eye, atol=1e-12)
    np.testing.assert_allclose((g.so3_left_jacobian_inv(phi) @ g.so3_left_jacobian(phi)).numpy(), eye, atol=1e-12)


def random_twists(n, dim, seed=2, scale=1.0):
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.normal(size=(n, dim)) * scale)


@pytest.mark.parametrize(
    "exp,log,adj,jl,jr,jli,jri,dim",
    [
        (g.se3_exp, g.se3_log, g.se3_adjoint, g.se3_left_jacobian, g.se3_right_jacobian,
         g.se3_left_jacobian_inv, g.se3_right_jacobian_inv, 6),
        (g.sim3_exp, g.sim3_log, g.sim3_adjoint, g.sim3_left_jacobian, g.sim3_right_jacobian,
         g.sim3_left_jacobian_inv, g.sim3_right_jacobian_inv, 7),
    ],
)
def test_group_exp_log_adjoint_jacobians(exp, log, adj, jl, jr, jli, jri, dim):
    xi = random_twists(30, dim, scale=0.8)
    t = exp(xi)
    np.testing.assert_allclose(log(t).numpy(), xi.numpy(), atol=1e-12)
    # Exp agrees with the matrix exponential of the Lie-algebra matrix.
    hat = g.se3_hat if dim == 6 else g.sim3_hat
    np.testing.assert_allclose(t.numpy(), torch.linalg.matrix_exp(hat(xi)).numpy(), atol=1e-12)
    # Adjoint: T Exp(d) T^-1 = Exp(Ad_T d).
    inv = g.se3_inverse if dim == 6 else g.sim3_inverse
    d = random_twists(30, dim, seed=5, scale=0.3)
    np.testing.assert_allclose(
        (t @ exp(d) @ inv(t)).numpy(), exp((adj(t) @ d[..., None])[..., 0]).numpy(), atol=1e-12
    )
    # Jacobians against numerical differentiation of the group log.
    num_l = numeric_jacobian(lambda x: log(exp(x) @ inv(t)), xi)
    num_r = numeric_jacobian(lambda x: log(inv(t) @ exp(x)), xi)
    np.testing.assert_allclose(jl(xi).numpy(), num_l.numpy(), atol=1e-7)
    np.testing.assert_allclose(jr(xi).numpy(), num_r.numpy(), atol=1e-7)
    eye = np.broadcast_to(np.eye(dim), (30, dim, dim))
    np.testing.assert_allclose((jli(xi) @ jl(xi)).numpy(), eye, atol=1e-10)
    np.testing.assert_allclose((jri(xi) @ jr(xi)).numpy(), eye, atol=1e-10)


@pytest.mark.parametrize("ad,dim", [(se3.se3_ad, 6), (sim3.sim3_ad, 7)])
def test_inverse_jacobian_series_matches_the_exact_inverse(ad, dim):
    """Small twists (as pose-graph residuals) take the Bernoulli series, large ones the exact inverse, in one
    batch; both invert the series left Jacobian."""
    xi = torch.cat((random_twists(40, dim, seed=3, scale=0.02), random_twists(20, dim, seed=4, scale=0.1),
                    random_twists(10, dim, seed=6, scale=1.5)))
    a = ad(xi)
    small = torch.linalg.matrix_norm(a) <= 0.5
    assert 0 < int(small.sum()) < len(xi)
    inv = se3.series_left_jacobian_inv(a)
    np.testing.assert_allclose(inv.numpy(), torch.linalg.inv(se3.series_left_jacobian(a)).numpy(), atol=1e-12)


def test_se3_act_inverse_compose():
    t = g.se3_exp(random_twists(10, 6))
    pts = torch.randn(10, 50, 3, dtype=D)
    moved = g.se3_act(t, pts)
    homog = torch.cat((pts, torch.ones(10, 50, 1, dtype=D)), -1)
    np.testing.assert_allclose(moved.numpy(), (homog @ t.transpose(-1, -2))[..., :3].numpy(), atol=1e-12)
    np.testing.assert_allclose(g.se3_act(g.se3_inverse(t), moved).numpy(), pts.numpy(), atol=1e-12)
    np.testing.assert_allclose(g.se3_compose(t, g.se3_inverse(t)).numpy(), np.broadcast_to(np.eye(4), (10, 4, 4)), atol=1e-12)


def test_sim3_scale_act_inverse():
    scale = torch.tensor([0.2, 1.0, 5.0], dtype=D)
    rot = g.so3_exp(random_rotvecs(3))
    trans = torch.randn(3, 3, dtype=D)
    s = g.sim3_from_srt(scale, rot, trans)
    np.testing.assert_allclose(g.sim3_scale(s).numpy(), scale.numpy(), rtol=1e-12)
    pts = torch.randn(3, 7, 3, dtype=D)
    expected = scale[:, None, None] * (pts @ rot.transpose(-1, -2)) + trans[:, None, :]
    np.testing.assert_allclose(g.sim3_act(s, pts).numpy(), expected.numpy(), atol=1e-12)
    np.testing.assert_allclose(g.sim3_act(g.sim3_inverse(s), expected).numpy(), pts.numpy(), atol=1e-12)
    np.testing.assert_allclose(g.sim3_log(s)[:, 6].numpy(), np.log(scale.numpy()), atol=1e-12)


def test_float32_and_autograd_are_finite_at_zero():
    phi = torch.zeros(4, 3, dtype=torch.float32, requires_grad=True)
    r = g.so3_exp(phi)
    assert r.dtype == torch.float32
    g.so3_log(r).sum().backward()
    assert torch.isfinite(phi.grad).all()
    xi = torch.zeros(2, 6, requires_grad=True)
    g.se3_log(g.se3_exp(xi)).square().sum().backward()
    assert torch.isfinite(xi.grad).all()


def test_interpolate_poses_slerp_midpoint():
    times = torch.tensor([0.0, 1.0], dtype=D)
    rots = g.so3_exp(torch.tensor([[0.0, 0, 0], [0, 0, 1.0]], dtype=D))
    pos = torch.tensor([[0.0, 0, 0], [2.0, 0, 0]], dtype=D)
    r, p = g.interpolate_poses(times, rots, pos, torch.tensor([0.25, 1.0], dtype=D))
    np.testing.assert_allclose(g.so3_log(r).numpy(), [[0, 0, 0.25], [0, 0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(p.numpy(), [[0.5, 0, 0], [2.0, 0, 0]], atol=1e-12)
    with pytest.raises(ValueError, match="span"):
        g.interpolate_poses(times, rots, pos, torch.tensor([1.5], dtype=D))
