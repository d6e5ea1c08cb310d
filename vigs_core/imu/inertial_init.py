"""Inertial-only initialisation (VIGS-SLAM Sec. 3.2; Campos et al., "Inertial-Only Optimization for
Visual-Inertial Initialization", ICRA 2020).

Given the up-to-scale camera poses ``T_wc,k`` of ``N`` keyframes and the IMU between them, estimate
the gravity direction ``R_wg`` (2 DoF), the log-scale ``sigma`` (``s = exp(sigma)`` multiplies the
camera positions), one velocity per keyframe and one bias ``(b_g, b_a)`` shared by the window (or,
with ``bias_random_walk``, one bias per keyframe tied to its neighbours by the random-walk term
``r_b = b_j - b_i`` of VIGS-SLAM Eq. (3), weighted by the random-walk covariance of each interval),
by minimising the inertial residuals of :mod:`vigs_core.imu.residual` plus bias priors with
Levenberg-Marquardt. Camera positions are held fixed. Camera rotations are either held fixed too
(default, as in VIGS-SLAM: their noise ``pose_rotation_std`` is pushed through the rotation
Jacobians into each factor's covariance) or (``refine_rotations=True``) receive a small correction
each with a zero-mean prior of that standard deviation: the gyro, far more precise over a keyframe
interval than a visual rotation, then averages independent rotation noise out instead of passing it
into gravity and scale (it assumes the noise is independent per keyframe, not drift).
Factors are weighted by the preintegration covariance plus the pose position noise; later weighting
rounds apply a Huber weight. Initial values come in closed form:

1. ``b_g``: Gauss-Newton on the rotation residuals alone (they do not depend on the other unknowns);
2. ``v_k``, ``g`` (3-vector) and ``s``: linear least squares, since with fixed rotations and biases
   ``v_j - v_i - g dt = R_i dv`` and ``s (p_wc,j - p_wc,i) + (R_wc,j - R_wc,i) p_cb - v_i dt - g dt^2/2
   = R_i dp`` are linear in them (Mur-Artal and Tardos, RA-L 2017, without the |g| constraint).

Trust figure: the covariance of ``(gravity angles, sigma)`` from the inverse Gauss-Newton Hessian at
the solution, scaled by the a-posteriori variance factor ``max(1, chi2 / dof)`` so unmodelled noise
widens it; the solution is flagged trustworthy when the standard deviations are under the configured
limits. The figure is only as honest as the noise model: EuRoC's datasheet densities understate the
vibrating platform's noise 4-9x (``vigs imu-check`` measures it), so pass measured densities.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.geometry import (
    hat,
    so3_exp,
    so3_left_jacobian,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
)
from vigs_core.imu.preintegration import Preintegrated, preintegrate_between
from vigs_core.imu.residual import body_states, gravity_rotation, inertial_residual
from vigs_core.types import ImuNoise, ImuSamples


@dataclass
class InertialInitConfig:
    """Settings of :func:`inertial_only_init`.

    Args:
        gravity: gravity magnitude (m/s^2).
        pose_rotation_std: assumed per-axis rotation noise of each input pose (rad): the prior of the
            rotation corrections, or (``refine_rotations=False``) propagated through the rotation
            Jacobians into every factor's covariance.
        pose_position_std: assumed metric position noise of each input pose (m), added to the position
            block of every factor's covariance (twice: both ends).
        prior_bias_gyro_std: standard deviation of the gyro-bias prior (rad/s).
        prior_bias_acc_std: standard deviation of the accelerometer-bias prior (m/s^2).
        max_iterations: Levenberg-Marquardt iterations per weighting round.
        weight_rounds: solves, each with the factor weights re-evaluated at the previous solution.
        huber_threshold: from the second round on, factors whose whitened residual norm exceeds this
            are down-weighted by ``threshold / norm`` (Huber); 0 disables.
        max_log_scale_std: trust limit on the standard deviation of ``sigma`` (0.01 ~ 1% in scale).
        max_gravity_std_deg: trust limit on the gravity-direction standard deviation (deg).
        scheme: preintegration scheme (see :mod:`vigs_core.imu.preintegration`).
        refine_rotations: estimate a small rotation correction per keyframe (prior
            ``pose_rotation_std``) instead of holding the rotations fixed and widening the factor
            covariances; the gyro then averages the rotation noise of the poses out.
        bias_random_walk: estimate one bias per keyframe, consecutive biases tied by the residual's
            random-walk term (covariance ``sigma_rw^2 dt`` from the ``ImuNoise`` random walks); the
            bias priors then act on the first keyframe's bias. Off: one bias for the whole window.
            A constant bias makes the solver trust the IMU's dead reckoning over the whole window;
            on real EuRoC data the bias wanders (the V1_01 ground-truth fit: about 0.012-0.016
            m/s^2/sqrt(s), 4-5x the datasheet random walk), so pass measured random walks with it.
    """

    gravity: float = 9.81
    pose_rotation_std: float = 0.005
    pose_position_std: float = 0.002
    prior_bias_gyro_std: float = 0.1
    prior_bias_acc_std: float = 0.1
    max_iterations: int = 30
    weight_rounds: int = 3
    huber_threshold: float = 5.0
    max_log_scale_std: float = 0.01
    max_gravity_std_deg: float = 1.0
    scheme: str = "closed_form"
    refine_rotations: bool = False
    bias_random_walk: bool = False


@dataclass
class InertialInit:
    """Result of the inertial-only initialisation.

    Attributes:
        R_wg: (3, 3) gravity-frame rotation; ``gravity_world = R_wg (0, 0, -g)`` (3,) m/s^2.
        scale: ``exp(log_scale)``; metric positions are ``scale * p_wc`` (+ lever arm).
        velocities: (N, 3) body velocities in the world frame (m/s).
        bias_gyro, bias_acc: (3,) rad/s, m/s^2, at the last keyframe (the same for every keyframe
            unless ``bias_random_walk``).
        rotation_corrections: (N, 3) left rotation increments applied to the camera rotations
            (``R_wc <- Exp(d) R_wc``; zero when ``refine_rotations`` is off).
        cov_gravity_scale: (3, 3) covariance of (2 gravity angles (rad), log-scale).
        log_scale_std, gravity_std_deg: marginal standard deviations (largest gravity axis).
        condition_number: of the Jacobi-scaled Hessian of all unknowns.
        chi2_per_dof: final weighted cost over the degrees of freedom.
        trustworthy: both standard deviations under the configured limits.
        linear_gravity_norm: ``|g|`` of the closed-form initial values (step 2 of the module docstring, which leaves
            the magnitude free): far from ``gravity``, the poses and the IMU disagree.
        iterations: LM iterations run.
        keyframe_biases: (N, 6) ``(b_g, b_a)`` of every keyframe.
    """

    R_wg: torch.Tensor
    gravity_world: torch.Tensor
    log_scale: float
    scale: float
    velocities: torch.Tensor
    bias_gyro: torch.Tensor
    bias_acc: torch.Tensor
    rotation_corrections: torch.Tensor
    cov_gravity_scale: torch.Tensor
    log_scale_std: float
    gravity_std_deg: float
    condition_number: float
    chi2_per_dof: float
    trustworthy: bool
    iterations: int
    keyframe_biases: torch.Tensor
    linear_gravity_norm: float = float("nan")


def _gyro_bias(pre: Preintegrated, R_b: torch.Tensor, iterations: int = 3) -> torch.Tensor:
    """Gauss-Newton for the gyro bias on the rotation residuals ``Log(dR(b_g)^T R_i^T R_j)``."""
    bg = pre.bias_gyro[0].clone()
    rel = R_b[:-1].transpose(-1, -2) @ R_b[1:]
    for _ in range(iterations):
        dbg = bg - pre.bias_gyro
        dR = pre.delta_R @ so3_exp((pre.J_R_bg @ dbg[..., None])[..., 0])
        E = dR.transpose(-1, -2) @ rel
        r = so3_log(E)
        J = -so3_right_jacobian_inv(r) @ E.transpose(-1, -2) @ so3_right_jacobian(
            (pre.J_R_bg @ dbg[..., None])[..., 0]) @ pre.J_R_bg
        H = (J.transpose(-1, -2) @ J).sum(0)
        g = (J.transpose(-1, -2) @ r[..., None]).sum(0)[:, 0]
        bg = bg - torch.linalg.solve(H, g)
    return bg


def _linear_velocity_gravity_scale(pre, T_wc, T_cb, bg):
    """Least squares for (v_0..v_{N-1}, g (3), s) with fixed rotations, b_g and b_a = 0."""
    f = dict(dtype=torch.float64, device=T_wc.device)
    n = T_wc.shape[0]
    R_b = T_wc[:, :3, :3] @ T_cb[:3, :3]
    p_wc = T_wc[:, :3, 3]
    arm = (T_wc[:, :3, :3] @ T_cb[:3, 3:4])[..., 0]  # lever arm R_wc p_cb (metric)
    _, dv, dp = pre.corrected(bg.expand(n - 1, 3), pre.bias_acc)
    dt = pre.dt
    P = 3 * n + 4
    A = torch.zeros(n - 1, 6, P, **f)
    b = torch.zeros(n - 1, 6, **f)
    eye = torch.eye(3, **f)
    idx = torch.arange(n - 1, device=T_wc.device)
    sig_v = pre.cov[:, 3:6, 3:6].diagonal(dim1=-2, dim2=-1).mean(-1).sqrt()
    sig_p = pre.cov[:, 6:9, 6:9].diagonal(dim1=-2, dim2=-1).mean(-1).sqrt()
    for k in range(3):  # rows: velocity equation, then position equation
        A[idx, k, 3 * idx + k] = -1.0
        A[idx, k, 3 * (idx + 1) + k] = 1.0
        A[idx, 3 + k, 3 * idx + k] = -dt
    A[:, 0:3, 3 * n:3 * n + 3] = -dt[:, None, None] * eye
    A[:, 3:6, 3 * n:3 * n + 3] = -0.5 * (dt * dt)[:, None, None] * eye
    A[:, 3:6, 3 * n + 3] = p_wc[1:] - p_wc[:-1]
    b[:, 0:3] = (R_b[:-1] @ dv[..., None])[..., 0]
    b[:, 3:6] = (R_b[:-1] @ dp[..., None])[..., 0] - (arm[1:] - arm[:-1])
    w = torch.cat((sig_v[:, None].expand(-1, 3), sig_p[:, None].expand(-1, 3)), 1)
    A, b = A / w[..., None], b / w
    x = torch.linalg.lstsq(A.reshape(-1, P), b.reshape(-1, 1)).solution[:, 0]
    return x[:3 * n].reshape(n, 3), x[3 * n:3 * n + 3], x[3 * n + 3]


def inertial_only_init(
    T_wc: torch.Tensor,
    stamps_ns: np.ndarray,
    imu: ImuSamples,
    noise: ImuNoise,
    T_cb: torch.Tensor,
    config: InertialInitConfig | None = None,
    bias_prior: torch.Tensor | None = None,
    between: Callable[[], None] | None = None,
) -> InertialInit:
    """Solve gravity direction, scale, velocities and biases from fixed up-to-scale keyframe poses.

    Args:
        T_wc: (N, 4, 4) camera-to-world poses of the keyframes, arbitrary world frame, positions up to scale.
        stamps_ns: (N,) increasing keyframe stamps (ns), inside the IMU's span.
        imu: IMU samples covering the keyframes.
        noise: IMU noise densities.
        T_cb: (4, 4) body-to-camera extrinsic (metric).
        bias_prior: (6,) mean ``(b_g, b_a)`` of the bias priors (default zero), e.g. the gyro bias of a
            static initialisation.
        between: called after each iteration (a live caller's yield point: over the scale check's keyframes the
            solve is long enough for a live frontend to miss frames otherwise).
    """
    cfg = config or InertialInitConfig()
    f = dict(dtype=torch.float64, device=T_wc.device)
    T_wc, T_cb = T_wc.to(**f), T_cb.to(**f)
    n = T_wc.shape[0]
    if n < 3 or len(stamps_ns) != n:
        raise ValueError(f"need N >= 3 keyframe poses with one stamp each, got {n} poses, {len(stamps_ns)} stamps")
    pre = preintegrate_between(imu, stamps_ns, noise, scheme=cfg.scheme, device=T_wc.device)
    R_b, _, _ = body_states(T_wc, T_cb, 1.0)
    bg = _gyro_bias(pre, R_b)
    vel, g_vec, s = _linear_velocity_gravity_scale(pre, T_wc, T_cb, bg)
    log_scale = torch.log(s) if s > 0 else torch.zeros((), **f)
    R_wg = gravity_rotation(g_vec)
    prior_mean = torch.zeros(6, **f) if bias_prior is None else torch.as_tensor(bias_prior).to(**f)
    walk = cfg.bias_random_walk
    nb = n if walk else 1  # bias blocks
    m = 15 if walk else 9  # residual rows used: a shared bias has r_b = b_j - b_i = 0
    bias = torch.cat((bg, prior_mean[3:])).expand(nb, 6).clone()

    prior_w = torch.tensor([cfg.prior_bias_gyro_std] * 3 + [cfg.prior_bias_acc_std] * 3, **f) ** -2
    refine = cfg.refine_rotations and cfg.pose_rotation_std > 0
    n_rot = 3 * n if refine else 0
    P = 3 + 3 * n + 6 * nb + n_rot
    c_bias, c_rot = 3 + 3 * n, 3 + 3 * n + 6 * nb  # first columns of the bias and rotation-correction blocks
    hat_p = hat(T_wc[:, :3, 3])

    def residuals(state):
        R_wg, log_scale, vel, bias, dphi = state
        T = T_wc
        if refine:  # corrected camera rotations Exp(dphi_k) R_wc,k at fixed camera positions
            T = T_wc.clone()
            T[:, :3, :3] = so3_exp(dphi) @ T_wc[:, :3, :3]
        b_i, b_j = (bias[:-1], bias[1:]) if walk else (bias.expand(n - 1, 6),) * 2
        return inertial_residual(pre, T[:-1], vel[:-1], b_i, T[1:], vel[1:], b_j, R_wg, log_scale, T_cb, cfg.gravity)

    def rotation_jacobians(res):
        """d r / d (left rotation increment of camera i / j at fixed camera position), (B, 9, 3) each."""
        jac = res.jacobians
        J_i = jac["pose_i"][:, :9, 3:] + jac["pose_i"][:, :9, :3] @ hat_p[:-1]
        J_j = jac["pose_j"][:, :9, 3:] + jac["pose_j"][:, :9, :3] @ hat_p[1:]
        return J_i, J_j

    def weights(res, robust: bool):
        """(n-1, m, m) information of each factor: IMU covariance, pose position noise and (unless the
        rotations are refined) the pose rotation noise pushed through the rotation Jacobians; with
        ``bias_random_walk`` also the block of the bias random walk over the interval."""
        cov = pre.cov[:, :9, :9].clone()
        if not refine:
            J_i, J_j = rotation_jacobians(res)
            cov = cov + cfg.pose_rotation_std**2 * (J_i @ J_i.transpose(-1, -2) + J_j @ J_j.transpose(-1, -2))
        cov[:, 6:9, 6:9] += 2.0 * cfg.pose_position_std**2 * torch.eye(3, **f)
        W = torch.linalg.inv(cov)
        if robust and cfg.huber_threshold > 0:  # Huber IRLS weight on the whitened residual norm
            r = res.residual[:, :9]
            norm = (r[:, None, :] @ W @ r[:, :, None])[:, 0, 0].clamp_min(0).sqrt()
            W = W * (cfg.huber_threshold / norm.clamp_min(cfg.huber_threshold))[:, None, None]
        if not walk:
            return W
        W15 = torch.zeros(n - 1, 15, 15, **f)
        W15[:, :9, :9] = W
        W15[:, 9:, 9:] = torch.linalg.inv(pre.cov[:, 9:, 9:])
        return W15

    def cost_of(res, state, W):
        bias, dphi = state[3], state[4]
        r = res.residual[:, :m]
        cost = (r[:, None, :] @ W @ r[:, :, None]).sum() + (prior_w * (bias[0] - prior_mean) ** 2).sum()
        if refine:
            cost = cost + (dphi * dphi).sum() / cfg.pose_rotation_std**2
        return float(cost)

    # the columns of the state each factor k touches: gravity (2), scale, v_k, v_k+1, b_k (, b_k+1) (, dphi_k,
    # dphi_k+1); its normal equations are built over these alone and scattered into the full system
    k_ = torch.arange(n - 1, device=T_wc.device)[:, None]
    b3, b6 = torch.arange(3, device=T_wc.device), torch.arange(6, device=T_wc.device)
    col_blocks = [b3.expand(n - 1, 3), 3 + 3 * k_ + b3, 3 + 3 * (k_ + 1) + b3]
    col_blocks += [c_bias + 6 * k_ + b6, c_bias + 6 * (k_ + 1) + b6] if walk else [(c_bias + b6).expand(n - 1, 6)]
    if refine:
        col_blocks += [c_rot + 3 * k_ + b3, c_rot + 3 * (k_ + 1) + b3]
    cols = torch.cat(col_blocks, 1)                                              # (n-1, c)

    def normal_equations(res, state, W):
        bias, dphi = state[3], state[4]
        jac = {name: value[:, :m] for name, value in res.jacobians.items()}
        r = res.residual[:, :m]
        blocks = [jac["gravity"], jac["log_scale"], jac["vel_i"], jac["vel_j"], jac["bias_i"]]
        if walk:
            blocks.append(jac["bias_j"])
        if refine:  # dphi enters through Exp(dphi): a change d gives the left increment J_l(dphi) d
            J_i, J_j = rotation_jacobians(res)
            Jl = so3_left_jacobian(dphi)
            pad = torch.zeros(n - 1, m - 9, 3, **f)
            blocks += [torch.cat((J_i @ Jl[:-1], pad), 1), torch.cat((J_j @ Jl[1:], pad), 1)]
        J = torch.cat(blocks, 2)                                                 # (n-1, m, c)
        JW = J.transpose(-1, -2) @ W
        H = torch.zeros(P * P, **f)
        H.index_add_(0, (cols[:, :, None] * P + cols[:, None, :]).reshape(-1), (JW @ J).reshape(-1))
        H = H.view(P, P)
        grad = torch.zeros(P, **f)
        grad.index_add_(0, cols.reshape(-1), (JW @ r[..., None]).reshape(-1))
        H[c_bias:c_bias + 6, c_bias:c_bias + 6] += torch.diag(prior_w)
        grad[c_bias:c_bias + 6] += prior_w * (bias[0] - prior_mean)
        if refine:
            H[c_rot:, c_rot:] += torch.eye(n_rot, **f) / cfg.pose_rotation_std**2
            grad[c_rot:] += dphi.reshape(-1) / cfg.pose_rotation_std**2
        return H, grad

    state = (R_wg, log_scale, vel, bias, torch.zeros(n, 3, **f))
    res = residuals(state)
    it = 0
    for round_ in range(cfg.weight_rounds):  # re-weight at the current solution, then solve again
        W = weights(res, robust=round_ > 0)
        cost = cost_of(res, state, W)
        lam = 1e-4
        for _ in range(cfg.max_iterations):
            it += 1
            H, grad = normal_equations(res, state, W)
            step = torch.linalg.solve(H + lam * torch.diag(H.diagonal()), -grad)
            cand = (
                state[0] @ so3_exp(torch.cat((step[0:2], torch.zeros(1, **f)))),
                state[1] + step[2],
                state[2] + step[3:c_bias].reshape(n, 3),
                state[3] + step[c_bias:c_rot].reshape(nb, 6),
                state[4] + step[c_rot:].reshape(n, 3) if refine else state[4],
            )
            res_c = residuals(cand)
            cost_c = cost_of(res_c, cand, W)
            if between is not None:
                between()
            if cost_c < cost:
                rel_change = (cost - cost_c) / max(cost, 1e-300)
                state, res, cost = cand, res_c, cost_c
                lam = max(lam / 10, 1e-10)
                if rel_change < 1e-10 or float(step.abs().max()) < 1e-10:
                    break
            else:
                lam *= 10
                if lam > 1e8:
                    break

    R_wg, log_scale, vel, bias, dphi = state
    W = weights(res, robust=cfg.weight_rounds > 1)
    cost = cost_of(res, state, W)
    H, _ = normal_equations(res, state, W)
    dof = max(m * (n - 1) + 6 + n_rot - P, 1)  # prior rows count as observations
    chi2_dof = cost / dof
    cov_all = torch.linalg.inv(H) * max(1.0, chi2_dof)
    cov_gs = cov_all[:3, :3]
    d = H.diagonal().clamp_min(1e-300).rsqrt()
    eig = torch.linalg.eigvalsh(d[:, None] * H * d[None, :])
    cond = float(eig[-1] / eig[0].clamp_min(1e-300))
    log_scale_std = float(cov_gs[2, 2].sqrt())
    gravity_std_deg = math.degrees(float(torch.linalg.eigvalsh(cov_gs[:2, :2])[-1].clamp_min(0).sqrt()))
    trust = log_scale_std < cfg.max_log_scale_std and gravity_std_deg < cfg.max_gravity_std_deg
    return InertialInit(
        R_wg=R_wg, gravity_world=R_wg @ torch.tensor([0.0, 0.0, -cfg.gravity], **f),
        log_scale=float(log_scale), scale=float(torch.exp(log_scale)), velocities=vel,
        bias_gyro=bias[-1, :3], bias_acc=bias[-1, 3:], rotation_corrections=dphi, cov_gravity_scale=cov_gs,
        log_scale_std=log_scale_std, gravity_std_deg=gravity_std_deg, condition_number=cond, chi2_per_dof=chi2_dof,
        trustworthy=bool(trust), iterations=it, keyframe_biases=bias.expand(n, 6).clone(),
        linear_gravity_norm=float(g_vec.norm()),
    )
