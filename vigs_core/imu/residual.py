"""The inertial factor of VIGS-SLAM Eq. (2)-(3) between keyframes ``i`` and ``j``, batched, with analytic
Jacobians (Forster et al. T-RO 2017, Sec. VI; ORB-SLAM3 / Campos et al. ICRA 2020 for gravity and scale).

States (per keyframe): camera pose ``T_wc`` (4x4, camera-to-world; its translation is up to the
global scale ``s = exp(sigma)``), body velocity ``v`` (3,) m/s in the world frame, bias
``b = (b_g, b_a)`` (6,). Globals: gravity-frame rotation ``R_wg`` (gravity in the world is
``g = R_wg (0, 0, -G)``) and log-scale ``sigma``. The camera-IMU extrinsic ``T_cb`` (body-to-camera,
metric, fixed) gives the body pose ``R_i = R_wc,i R_cb``, ``p_i = s p_wc,i + R_wc,i p_cb``
(``T_cb = I`` to pass body poses directly).

Residual (15,), order ``(r_R, r_v, r_p, r_bg, r_ba)``, with ``dR, dv, dp`` the preintegrated deltas
corrected to ``b_i`` to first order::

    r_R = Log(dR^T R_i^T R_j)
    r_v = R_i^T (v_j - v_i - g dt) - dv
    r_p = R_i^T (p_j - p_i - v_i dt - g dt^2 / 2) - dp
    r_b = b_j - b_i

Perturbation conventions of the Jacobians (all first order):

* ``pose_i``, ``pose_j`` (.., 15, 6): left SE(3) perturbation of the camera pose, project convention
  ``T_wc <- Exp(xi) T_wc`` with ``xi = (rho, phi)`` (translation first, world frame). Callers that keep
  ``T_cw`` with ``T_cw <- Exp(xi') T_cw`` chain with ``J_cw = -J_wc Ad(T_wc)``.
* ``vel_i``, ``vel_j`` (.., 15, 3): ``v <- v + dv``. ``bias_i``, ``bias_j`` (.., 15, 6): ``b <- b + db``.
* ``gravity`` (.., 15, 2): ``R_wg <- R_wg Exp((a, b, 0))``, 2 DoF: rotation about the gravity axis
  does not change ``g`` and is left out.
* ``log_scale`` (.., 15, 1): ``sigma <- sigma + d``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.arrays import host
from vigs_core.geometry import hat, so3_log, so3_right_jacobian, so3_right_jacobian_inv
from vigs_core.imu.preintegration import Preintegrated

GRAVITY = 9.81


@dataclass
class InertialResidual:
    """Residuals, Jacobians and covariance of a batch of inertial factors.

    Attributes:
        residual: (B, 15) ``(r_R, r_v, r_p, r_bg, r_ba)``.
        jacobians: name -> (B, 15, n): ``pose_i``/``pose_j`` (6), ``vel_i``/``vel_j`` (3),
            ``bias_i``/``bias_j`` (6), ``gravity`` (2), ``log_scale`` (1).
        cov: (B, 15, 15) measurement covariance (the preintegration covariance); weight by its inverse.
    """

    residual: torch.Tensor
    jacobians: dict[str, torch.Tensor]
    cov: torch.Tensor

    def chi2(self) -> torch.Tensor:
        """(B,) Mahalanobis squared norms ``r^T Cov^-1 r``."""
        sol = torch.linalg.solve(self.cov, self.residual[..., None])
        return (self.residual[..., None] * sol).sum((-1, -2))


def gravity_rotation(direction: torch.Tensor) -> torch.Tensor:
    """Minimal rotation ``R_wg`` (3, 3) with ``R_wg (0, 0, -1) = direction / |direction|``."""
    d = direction / direction.norm()
    down = torch.tensor([0.0, 0.0, -1.0], dtype=d.dtype, device=d.device)
    axis = torch.linalg.cross(down, d)
    s, c = axis.norm(), (down * d).sum()
    if s < 1e-12:
        return torch.eye(3, dtype=d.dtype, device=d.device) if c > 0 else torch.diag(
            torch.tensor([1.0, -1.0, -1.0], dtype=d.dtype, device=d.device))
    k = hat(axis / s)
    return torch.eye(3, dtype=d.dtype, device=d.device) + s * k + (1 - c) * (k @ k)


def body_states(T_wc, T_cb, scale):
    """Body rotation (B,3,3), metric body position (B,3) and scaled camera position (B,3) from camera poses
    (torch tensors or NumPy arrays) and the scale ``s = exp(sigma)``."""
    R_wc, p_wc = T_wc[..., :3, :3], T_wc[..., :3, 3]
    R_wb = R_wc @ T_cb[:3, :3]
    p_wb = scale * p_wc + (R_wc @ T_cb[:3, 3:4])[..., 0]
    return R_wb, p_wb, scale * p_wc


def inertial_residual(
    pre: Preintegrated,
    T_wc_i: torch.Tensor,
    v_i: torch.Tensor,
    b_i: torch.Tensor,
    T_wc_j: torch.Tensor,
    v_j: torch.Tensor,
    b_j: torch.Tensor,
    R_wg: torch.Tensor,
    log_scale: torch.Tensor,
    T_cb: torch.Tensor,
    gravity: float = GRAVITY,
    jacobians: bool = True,
) -> InertialResidual:
    """Evaluate the inertial factors (see the module docstring for maths and conventions).

    The arithmetic runs in float64 NumPy on the host (a window's factors are a few hundred operations on
    arrays of a handful of rows, where torch's per-operation overhead was most of the cost: about 2 ms per
    call through torch, several calls per BA iteration); the results are float64 tensors on the device of
    ``T_wc_i``.

    Args:
        pre: batched preintegration (``B`` intervals, e.g. from ``preintegrate_between``).
        T_wc_i, T_wc_j: (B, 4, 4) camera poses; v_i, v_j: (B, 3); b_i, b_j: (B, 6) ``(b_g, b_a)``.
        R_wg: (3, 3); log_scale: () tensor; T_cb: (4, 4) body-to-camera; gravity: |g| (m/s^2).
        jacobians: False returns the residuals alone (``jacobians`` empty): a cost evaluation (an LM trial
            step) needs no Jacobians, which are most of the work.
    """
    device = T_wc_i.device if isinstance(T_wc_i, torch.Tensor) else torch.device("cpu")
    out = lambda x: torch.from_numpy(x).to(device)  # noqa: E731
    P = pre.host()
    T_wc_i, v_i, b_i, T_wc_j, v_j, b_j, R_wg, T_cb = (
        host(x, np.float64) for x in (T_wc_i, v_i, b_i, T_wc_j, v_j, b_j, R_wg, T_cb))
    s = float(np.exp(host(log_scale)))
    R_i, p_i, sp_i = body_states(T_wc_i, T_cb, s)
    R_j, p_j, sp_j = body_states(T_wc_j, T_cb, s)
    g_frame = np.array([0.0, 0.0, -gravity])
    g = R_wg @ g_frame
    dt = P.dt[..., None]
    dR, dv, dp = P.corrected(b_i[..., :3], b_i[..., 3:])
    Rit = R_i.swapaxes(-1, -2)
    mv = lambda m, x: (m @ x[..., None])[..., 0]  # noqa: E731

    E = dR.swapaxes(-1, -2) @ Rit @ R_j
    r_R = so3_log(E)
    x_v = v_j - v_i - g * dt
    x_p = p_j - p_i - v_i * dt - 0.5 * g * dt * dt
    r_v = mv(Rit, x_v) - dv
    r_p = mv(Rit, x_p) - dp
    r_b = b_j - b_i
    residual = np.concatenate((r_R, r_v, r_p, r_b), -1)
    if not jacobians:
        return InertialResidual(out(residual), {}, pre.cov)

    B = residual.shape[0]
    Jinv = so3_right_jacobian_inv(r_R)
    JRj = Jinv @ R_j.swapaxes(-1, -2)
    # each Jacobian is (B, 15, n), rows (r_R, r_v, r_p, r_b); the blocks that are not zero are filled in
    pose_i, pose_j = np.zeros((B, 15, 6)), np.zeros((B, 15, 6))   # (rho, phi) columns
    pose_i[:, 0:3, 3:] = -JRj
    pose_i[:, 3:6, 3:] = Rit @ hat(x_v)
    pose_i[:, 6:9, :3] = -s * Rit
    pose_i[:, 6:9, 3:] = Rit @ (hat(x_p) + hat(p_i))
    pose_j[:, 0:3, 3:] = JRj
    pose_j[:, 6:9, :3] = s * Rit
    pose_j[:, 6:9, 3:] = -Rit @ hat(p_j)
    vel_i, vel_j = np.zeros((B, 15, 3)), np.zeros((B, 15, 3))
    vel_i[:, 3:6], vel_i[:, 6:9], vel_j[:, 3:6] = -Rit, -Rit * dt[..., None], Rit
    dbg = b_i[..., :3] - P.bias_gyro
    bias_i, bias_j = np.zeros((B, 15, 6)), np.zeros((B, 15, 6))
    bias_i[:, 0:3, :3] = -Jinv @ E.swapaxes(-1, -2) @ so3_right_jacobian(mv(P.J_R_bg, dbg)) @ P.J_R_bg
    bias_i[:, 3:6, :3], bias_i[:, 3:6, 3:] = -P.J_v_bg, -P.J_v_ba
    bias_i[:, 6:9, :3], bias_i[:, 6:9, 3:] = -P.J_p_bg, -P.J_p_ba
    bias_i[:, 9:15] = -np.eye(6)
    bias_j[:, 9:15] = np.eye(6)
    dg = (-R_wg @ hat(g_frame))[:, :2]  # d g / d (a, b), (3, 2)
    gravity_j = np.zeros((B, 15, 2))
    gravity_j[:, 3:6] = -(Rit @ dg) * dt[..., None]
    gravity_j[:, 6:9] = -0.5 * (Rit @ dg) * (dt * dt)[..., None]
    scale_j = np.zeros((B, 15, 1))
    scale_j[:, 6:9, 0] = mv(Rit, sp_j - sp_i)
    jac = dict(pose_i=pose_i, pose_j=pose_j, vel_i=vel_i, vel_j=vel_j, bias_i=bias_i, bias_j=bias_j,
               gravity=gravity_j, log_scale=scale_j)
    return InertialResidual(out(residual), {k: out(v) for k, v in jac.items()}, pre.cov)
