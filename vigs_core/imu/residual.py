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

import torch

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


def body_states(
    T_wc: torch.Tensor, T_cb: torch.Tensor, log_scale: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Body rotation (B,3,3), metric body position (B,3) and scaled camera position (B,3) from camera poses."""
    R_wc, p_wc = T_wc[..., :3, :3], T_wc[..., :3, 3]
    s = torch.exp(log_scale)
    R_wb = R_wc @ T_cb[:3, :3]
    p_wb = s * p_wc + (R_wc @ T_cb[:3, 3:4])[..., 0]
    return R_wb, p_wb, s * p_wc


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

    Args:
        pre: batched preintegration (``B`` intervals, e.g. from ``preintegrate_between``).
        T_wc_i, T_wc_j: (B, 4, 4) camera poses; v_i, v_j: (B, 3); b_i, b_j: (B, 6) ``(b_g, b_a)``.
        R_wg: (3, 3); log_scale: () tensor; T_cb: (4, 4) body-to-camera; gravity: |g| (m/s^2).
        jacobians: False returns the residuals alone (``jacobians`` empty): a cost evaluation (an LM trial
            step) needs no Jacobians, which are most of the work.
    """
    f = dict(dtype=torch.float64, device=T_wc_i.device)
    T_cb, R_wg = T_cb.to(**f), R_wg.to(**f)
    log_scale = torch.as_tensor(log_scale, **f)
    R_i, p_i, sp_i = body_states(T_wc_i, T_cb, log_scale)
    R_j, p_j, sp_j = body_states(T_wc_j, T_cb, log_scale)
    g_frame = torch.tensor([0.0, 0.0, -gravity], **f)
    g = R_wg @ g_frame
    dt = pre.dt[..., None]
    dR, dv, dp = pre.corrected(b_i[..., :3], b_i[..., 3:])
    Rit = R_i.transpose(-1, -2)
    mv = lambda m, x: (m @ x[..., None])[..., 0]  # noqa: E731

    E = dR.transpose(-1, -2) @ Rit @ R_j
    r_R = so3_log(E)
    x_v = v_j - v_i - g * dt
    x_p = p_j - p_i - v_i * dt - 0.5 * g * dt * dt
    r_v = mv(Rit, x_v) - dv
    r_p = mv(Rit, x_p) - dp
    r_b = b_j - b_i
    residual = torch.cat((r_R, r_v, r_p, r_b), -1)
    if not jacobians:
        return InertialResidual(residual, {}, pre.cov)

    B = residual.shape[0]
    zero = torch.zeros(B, 3, 3, **f)
    Jinv = so3_right_jacobian_inv(r_R)
    JRj = Jinv @ R_j.transpose(-1, -2)

    def rows(*blocks):  # stack 5 row blocks (B, 3, n) into (B, 15, n)
        return torch.cat(blocks, dim=-2)

    # pose_i: (rho, phi) columns
    pose_i = rows(
        torch.cat((zero, -JRj), -1),
        torch.cat((zero, Rit @ hat(x_v)), -1),
        torch.cat((-torch.exp(log_scale) * Rit, Rit @ (hat(x_p) + hat(p_i))), -1),
        torch.zeros(B, 6, 6, **f),
    )
    pose_j = rows(
        torch.cat((zero, JRj), -1),
        torch.zeros(B, 3, 6, **f),
        torch.cat((torch.exp(log_scale) * Rit, -Rit @ hat(p_j)), -1),
        torch.zeros(B, 6, 6, **f),
    )
    vel_i = rows(zero, -Rit, -Rit * dt[..., None], torch.zeros(B, 6, 3, **f))
    vel_j = rows(zero, Rit, zero, torch.zeros(B, 6, 3, **f))
    dbg = b_i[..., :3] - pre.bias_gyro
    d_rR_dbg = -Jinv @ E.transpose(-1, -2) @ so3_right_jacobian(mv(pre.J_R_bg, dbg)) @ pre.J_R_bg
    eye6 = torch.eye(6, **f).expand(B, 6, 6)
    bias_i = rows(
        torch.cat((d_rR_dbg, zero), -1),
        torch.cat((-pre.J_v_bg, -pre.J_v_ba), -1),
        torch.cat((-pre.J_p_bg, -pre.J_p_ba), -1),
        -eye6,
    )
    bias_j = rows(torch.zeros(B, 9, 6, **f), eye6)
    dg = (-R_wg @ hat(g_frame))[:, :2]  # d g / d (a, b), (3, 2)
    gravity_j = rows(
        torch.zeros(B, 3, 2, **f), -(Rit @ dg) * dt[..., None], -0.5 * (Rit @ dg) * (dt * dt)[..., None],
        torch.zeros(B, 6, 2, **f),
    )
    scale_j = rows(torch.zeros(B, 6, 1, **f), mv(Rit, sp_j - sp_i)[..., None], torch.zeros(B, 6, 1, **f))
    jac = dict(pose_i=pose_i, pose_j=pose_j, vel_i=vel_i, vel_j=vel_j, bias_i=bias_i, bias_j=bias_j,
               gravity=gravity_j, log_scale=scale_j)
    return InertialResidual(residual, jac, pre.cov)
