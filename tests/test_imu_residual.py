"""Inertial factor: zero at the truth, analytic Jacobians against central differences, chi2 growth."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vigs_core.geometry import se3_exp, se3_from_rt, se3_inverse, so3_exp
from vigs_core.imu.analytic_motion import AnalyticMotion
from vigs_core.imu.preintegration import preintegrate_between, preintegrate_measurements, stack_preintegrated
from vigs_core.imu.residual import gravity_rotation, inertial_residual
from vigs_core.types import ImuNoise

torch.set_num_threads(1)  # the test machine is shared; one thread each is fastest

F64 = torch.float64


def random_problem(seed: int = 0, batch: int = 3):
    gen = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.randn(*s, dtype=F64, generator=gen)  # noqa: E731
    pres = []
    for _ in range(batch):
        k = 20
        pres.append(preintegrate_measurements(
            torch.full((k,), 0.005, dtype=F64), rnd(k, 3), rnd(k, 3) + torch.tensor([0, 0, 9.81], dtype=F64),
            ImuNoise(), rnd(3) * 0.01, rnd(3) * 0.1))
    state = dict(
        T_wc_i=se3_exp(rnd(batch, 6)), v_i=rnd(batch, 3), b_i=rnd(batch, 6) * 0.05,
        T_wc_j=se3_exp(rnd(batch, 6)), v_j=rnd(batch, 3), b_j=rnd(batch, 6) * 0.05,
        R_wg=so3_exp(rnd(3)), log_scale=torch.tensor(0.3, dtype=F64), T_cb=se3_exp(rnd(6) * 0.3),
    )
    return stack_preintegrated(pres), state


def perturb(state: dict, name: str, k: int, e: float) -> dict:
    """Apply the documented perturbation of column k of Jacobian ``name``."""
    s = dict(state)
    batch = state["v_i"].shape[0]
    if name.startswith("pose"):
        key = "T_wc_" + name[-1]
        d = torch.zeros(batch, 6, dtype=F64)
        d[:, k] = e
        s[key] = se3_exp(d) @ state[key]
    elif name.startswith("vel") or name.startswith("bias"):
        key = ("v_" if name.startswith("vel") else "b_") + name[-1]
        d = torch.zeros_like(state[key])
        d[:, k] = e
        s[key] = state[key] + d
    elif name == "gravity":
        d = torch.zeros(3, dtype=F64)
        d[k] = e
        s["R_wg"] = state["R_wg"] @ so3_exp(d)
    else:
        s["log_scale"] = state["log_scale"] + e
    return s


@pytest.mark.parametrize("name", ["pose_i", "pose_j", "vel_i", "vel_j", "bias_i", "bias_j", "gravity", "log_scale"])
def test_jacobians_match_central_differences(name):
    pre, state = random_problem()
    jac = inertial_residual(pre, **state).jacobians[name]
    eps = 1e-6
    numeric = torch.stack([
        (inertial_residual(pre, **perturb(state, name, k, eps), jacobians=False).residual
         - inertial_residual(pre, **perturb(state, name, k, -eps), jacobians=False).residual) / (2 * eps)
        for k in range(jac.shape[-1])
    ], -1)
    assert float((numeric - jac).abs().max()) < 1e-7 * max(1.0, float(jac.abs().max()))


def test_residual_without_jacobians_is_the_same_residual():
    pre, state = random_problem(seed=3, batch=4)
    full, only = inertial_residual(pre, **state), inertial_residual(pre, **state, jacobians=False)
    assert torch.equal(full.residual, only.residual) and only.jacobians == {}
    assert torch.equal(full.chi2(), only.chi2())


def _truth_states(motion, stamps_ns, T_cb, log_scale):
    """Camera poses (positions divided by the scale), body velocities, from analytic motion."""
    R, p, v = motion.state(stamps_ns * 1e-9)
    T_wb = se3_from_rt(R, p)
    T_wc = T_wb @ se3_inverse(T_cb)
    s = torch.exp(log_scale)
    T_wc = T_wc.clone()
    T_wc[:, :3, 3] = T_wc[:, :3, 3] / s  # metric body position = s p_wc + R_wc p_cb
    return T_wc, v


def test_residual_vanishes_at_the_truth_and_grows_when_perturbed():
    motion = AnalyticMotion.default()
    imu = motion.imu(np.arange(0, 3_000_000_000, 1_000_000))
    stamps = np.array([500_000_123, 900_000_456, 1_400_000_789, 2_000_001_011])
    pre = preintegrate_between(imu, stamps, ImuNoise())
    T_cb = se3_exp(torch.tensor([0.05, -0.02, 0.01, 0.1, -0.2, 1.5], dtype=F64))
    log_scale = torch.tensor(np.log(2.5), dtype=F64)
    T_wc, v = _truth_states(motion, stamps, T_cb, log_scale)
    # the world of the poses is rotated; gravity in it is R_wg (0, 0, -9.81)
    R_x = se3_from_rt(so3_exp(torch.tensor([0.3, -0.4, 0.2], dtype=F64)), torch.zeros(3, dtype=F64))
    T_wc = R_x @ T_wc
    v = (R_x[:3, :3] @ v[..., None])[..., 0]
    R_wg = gravity_rotation(R_x[:3, :3] @ torch.tensor([0.0, 0.0, -1.0], dtype=F64))
    b = torch.zeros(len(stamps) - 1, 6, dtype=F64)
    args = dict(v_i=v[:-1], b_i=b, v_j=v[1:], b_j=b, R_wg=R_wg, log_scale=log_scale, T_cb=T_cb)
    res = inertial_residual(pre, T_wc[:-1], T_wc_j=T_wc[1:], **args)
    assert float(res.residual.abs().max()) < 1e-6
    wrong_scale = dict(args, log_scale=log_scale + 0.01)
    bad = inertial_residual(pre, T_wc[:-1], T_wc_j=T_wc[1:], **wrong_scale)
    assert bool((bad.chi2() > 1e3 * res.chi2().clamp_min(1e-12)).all())


def test_gravity_rotation_maps_down_to_the_direction():
    for d in ([0.3, -0.2, -0.9], [0.0, 0.0, 1.0], [0.0, 0.0, -2.0]):
        d = torch.tensor(d, dtype=F64)
        R = gravity_rotation(d)
        assert torch.allclose(R @ torch.tensor([0.0, 0.0, -1.0], dtype=F64), d / d.norm(), atol=1e-12)
        assert torch.allclose(R @ R.T, torch.eye(3, dtype=F64), atol=1e-12)
