"""Inertial residual blocks as :class:`~vigs_core.solver.dense_ba.AdditionalTerms` of dense BA (VIGS-SLAM
Sec. 3.3: one normal equation per iteration over visual and inertial terms).

For the ``n`` keyframes of the window (consecutive in time) the terms add, per interval ``(k, k+1)``, the
inertial residual of VIGS-SLAM Eq. (2)-(3) (:func:`vigs_core.imu.residual.inertial_residual`: rotation,
velocity, position and bias smoothness ``b_{k+1} - b_k``) weighted by the inverse preintegration covariance,
plus a zero-mean prior on every bias state and, optionally, an anchor prior holding the velocity and bias of
the window's fixed keyframes (:class:`AnchorPrior`) and a marginalisation prior on states of the window that
carries the information of the keyframes that left it (:class:`MarginalPrior`)::

    cost = 1/2 w sum_k r_k^T Cov_k^-1 r_k  +  1/2 sum_b |b / sigma_prior|^2
           + 1/2 sum_{k anchored} (|v_k - v_k^0|^2 / sigma_v^2 + |b_k - b_k^0|^2 / sigma_b^2)
           + 1/2 delta^T H_p delta - g_p^T delta + c_p,      delta = x [-] x_lin (marginalisation prior)

Extra state layout (appended after the ``6n`` pose columns of the reduced camera system)::

    [v_0 .. v_{n-1} (3n) | biases (6n per keyframe, 6 global, 0 not estimated) | gravity (2, optional) |
     log-scale (1, optional)]

Poses: the solver keeps world->camera poses ``T_cw`` with left perturbations ``T_cw <- Exp(xi) T_cw``; the
residual's Jacobians are for ``T_wc <- Exp(xi') T_wc``. Since ``(Exp(xi) T_cw)^-1 = T_wc Exp(-xi) =
Exp(-Ad(T_wc) xi) T_wc``, the chain rule gives ``J_cw = -J_wc Ad(T_wc)``. The camera-IMU extrinsic enters as
``T_cb`` (body->camera; EuRoC's ``T_BS`` of cam0 is ``T_bc``, so ``T_cb = T_BS^-1``).

The solver solves ``H dx = g`` and applies ``+dx``, so with ``J = dr/dx`` the terms return
``H = J^T W J`` and ``g = -J^T W r`` (Gauss-Newton).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from vigs_core.geometry import se3_adjoint, se3_inverse, se3_left_jacobian_inv, se3_log, so3_exp
from vigs_core.imu.preintegration import Preintegrated
from vigs_core.imu.residual import InertialResidual, inertial_residual


@dataclass
class InertialState:
    """Inertial states of the window's ``n`` keyframes.

    Attributes:
        velocities: (n, 3) body velocities in the world frame (map units per second; m/s once metric).
        biases: (n, 6) per-keyframe ``(b_g rad/s, b_a m/s^2)``, or (1, 6) for one global bias.
        R_wg: (3, 3) gravity-frame rotation, gravity in the world ``R_wg (0, 0, -|g|)``.
        log_scale: () ``sigma``, metric camera positions are ``exp(sigma) p_wc``.
    """

    velocities: torch.Tensor
    biases: torch.Tensor
    R_wg: torch.Tensor
    log_scale: torch.Tensor


@dataclass
class AnchorPrior:
    """Prior holding the velocity (and per-keyframe bias) of anchored keyframes at given values: the inertial
    counterpart of the fixed poses of a sliding window (keyframes held constant keep their velocity and bias
    too, so the window cannot trade the metric scale against the velocities and biases).

    Attributes:
        mask: (n,) bool, anchored keyframes; velocities: (n, 3) and biases: (n, 6) values to hold (rows of
        unanchored keyframes unused); velocity_std: m/s; bias_std: (6,) rad/s x3, m/s^2 x3.
    """

    mask: torch.Tensor
    velocities: torch.Tensor
    biases: torch.Tensor
    velocity_std: float
    bias_std: torch.Tensor


def state_columns(index: list[int], n: int, estimate_bias: bool, per_keyframe_bias: bool) -> torch.Tensor:
    """Columns of the keyframes at window positions ``index`` in the layout over ``n`` keyframes
    ``[xi (6n) | v (3n) | biases]`` (module docstring; no gravity or scale): their poses, then their
    velocities, then their biases (all 6 columns of a global bias)."""
    idx = torch.as_tensor(index, dtype=torch.long)
    a = torch.arange
    cols = [(6 * idx[:, None] + a(6)).reshape(-1), (6 * n + 3 * idx[:, None] + a(3)).reshape(-1)]
    if estimate_bias:
        cols.append((9 * n + 6 * idx[:, None] + a(6)).reshape(-1) if per_keyframe_bias else 9 * n + a(6))
    return torch.cat(cols)


def window_biases(biases: torch.Tensor, index: list[int] | torch.Tensor, estimate_bias: bool,
                  per_keyframe_bias: bool) -> torch.Tensor:
    """The bias rows that belong to the keyframes at window positions ``index``: theirs (per-keyframe biases),
    the one global bias, or none ((0, 6), biases not estimated)."""
    if not estimate_bias:
        return biases[:0]
    return biases[index] if per_keyframe_bias else biases


@dataclass
class MarginalPrior:
    """Gaussian prior on window states left by marginalising keyframes out of the window (Schur complement of the
    linearised factors of the departing keyframe; :func:`vigs_core.vio.marginalization.marginalize_keyframe`).

    Over the prior's ``K`` keyframes its state ``delta`` has the layout of :class:`InertialTerms` over ``K``
    keyframes without gravity and scale, ``[xi (6K) | v (3K) | biases (6K per keyframe, 6 global, 0)]``, with
    ``delta`` the difference from the linearisation point: ``xi_k = Log(T_cw,k T_cw,k^lin^-1)`` (left
    perturbation of the world->camera pose, translation first), ``v - v^lin``, ``b - b^lin``. The cost is

        c(delta) = 1/2 delta^T H delta - g^T delta + c0,   c0 = 1/2 g^T H^+ g   (minimum 0),

    so the solver's gradient and Hessian are ``A^T (g - H delta)`` and ``A^T H A`` with ``A`` the Jacobian of
    ``delta`` by the solver's increments: ``J_l^-1(xi_k)`` for the poses (``Exp(e) Exp(xi) = Exp(xi + J_l^-1(xi) e
    + O(e^2))``), identity for velocities and biases (first-estimate linearisation: ``H`` and ``g`` stay those
    of the marginalisation point, only ``delta`` moves).

    Attributes:
        ids: keyframe ids of the prior's ``K`` keyframes (ascending); poses (K, 4, 4), velocities (K, 3) and
            biases (K, 6) per keyframe or (1, 6) global, or (0, 6) not estimated: the linearisation point;
        H: (D, D) information; g: (D,) gradient at the linearisation point; c0: constant of the cost.
    """

    ids: list[int]
    poses: torch.Tensor
    velocities: torch.Tensor
    biases: torch.Tensor
    H: torch.Tensor
    g: torch.Tensor
    c0: float

    def delta(self, poses: torch.Tensor, velocities: torch.Tensor, biases: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """``delta`` (D,) at the given states of the prior's keyframes (poses (K, 4, 4), velocities (K, 3),
        biases like :attr:`biases`) and the pose tangents' inverse left Jacobians (K, 6, 6)."""
        xi = se3_log(poses.to(torch.float64) @ se3_inverse(self.poses))
        d = torch.cat((xi.reshape(-1), (velocities - self.velocities).reshape(-1),
                       (biases - self.biases).reshape(-1)))
        return d, se3_left_jacobian_inv(xi)

    def cost(self, delta: torch.Tensor) -> torch.Tensor:
        """``1/2 delta^T H delta - g^T delta + c0`` (scalar)."""
        return 0.5 * delta @ (self.H @ delta) - self.g @ delta + self.c0

    def linearized(self, poses: torch.Tensor, velocities: torch.Tensor, biases: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Hessian ``A^T H A`` (D, D) and gradient ``A^T (g - H delta)`` (D,) in the solver's increments, and
        ``delta`` (D,), at the given states (as :meth:`delta`; ``A`` the class docstring's Jacobian)."""
        d, Jl_inv = self.delta(poses, velocities, biases)
        A = torch.eye(d.shape[0], dtype=torch.float64, device=d.device)
        K = Jl_inv.shape[0]
        A[:6 * K, :6 * K] = torch.block_diag(*Jl_inv)
        return A.T @ self.H @ A, A.T @ (self.g - self.H @ d), d


class InertialTerms:
    """Inertial factors between consecutive window keyframes (see the module docstring).

    Args:
        pre: batched preintegration of the ``n - 1`` intervals (``stack_preintegrated`` /
            ``preintegrate_between``), interval ``k`` from keyframe ``k`` to ``k + 1``.
        T_cb: (4, 4) body->camera extrinsic (metric).
        estimate_bias: biases are states (else held at ``state.biases``).
        per_keyframe_bias: one bias per keyframe (``state.biases`` (n, 6)); else one global (1, 6).
        estimate_gravity: the gravity direction (2 DoF) is a state.
        estimate_scale: the log-scale is a state.
        gravity: |g|, m/s^2.
        weight: multiplies the inertial information matrices.
        interval_weight: optional (n - 1,) factor per interval on top of ``weight``; 0 drops an interval (an IMU
            gap inside it: its preintegration is no measurement).
        bias_prior_std: (6,) standard deviations of the zero-mean bias prior (rad/s x3, m/s^2 x3).
        anchor: optional :class:`AnchorPrior` on the velocities (and per-keyframe biases) of anchored keyframes.
        marginal: optional :class:`MarginalPrior`; ``marginal_index`` (K,) the window positions of its keyframes.
    """

    def __init__(self, pre: Preintegrated, T_cb: torch.Tensor, *, estimate_bias: bool = True,
                 per_keyframe_bias: bool = True, estimate_gravity: bool = False, estimate_scale: bool = False,
                 gravity: float = 9.81, weight: float = 1.0, bias_prior_std: torch.Tensor | None = None,
                 anchor: AnchorPrior | None = None, marginal: MarginalPrior | None = None,
                 marginal_index: list[int] | None = None, interval_weight: torch.Tensor | None = None) -> None:
        if pre.delta_R.dim() != 3:
            raise ValueError(f"InertialTerms needs a batched Preintegrated (B, 3, 3), got {tuple(pre.delta_R.shape)}")
        self.pre = pre
        self.n = pre.delta_R.shape[0] + 1
        f = dict(dtype=torch.float64, device=pre.delta_R.device)
        self.T_cb = torch.as_tensor(T_cb).to(**f)
        self.estimate_bias = estimate_bias
        self.per_keyframe_bias = per_keyframe_bias
        self.estimate_gravity = estimate_gravity
        self.estimate_scale = estimate_scale
        self.gravity = gravity
        cov = pre.cov.clone()
        if not (estimate_bias and per_keyframe_bias):
            cov = cov[:, :9, :9]  # no bias-smoothness rows: the bias is shared or constant
        eye = torch.eye(cov.shape[-1], **f)
        self.info = weight * torch.linalg.inv(cov + 1e-18 * eye)
        if interval_weight is not None:
            self.info = self.info * torch.as_tensor(interval_weight, **f)[:, None, None]
        prior = torch.tensor([0.1] * 3 + [0.5] * 3, **f) if bias_prior_std is None else bias_prior_std.to(**f)
        self.prior_info = prior ** -2
        self.anchor = anchor
        self.marginal = marginal
        n_bias = (6 * self.n if per_keyframe_bias else 6) if estimate_bias else 0
        self.off_vel = 6 * self.n
        self.off_bias = self.off_vel + 3 * self.n
        self.off_grav = self.off_bias + n_bias
        self.off_scale = self.off_grav + (2 if estimate_gravity else 0)
        self.dim = self.off_scale + (1 if estimate_scale else 0) - 6 * self.n
        if marginal is not None:
            self._marginal_setup(marginal, marginal_index)

    def _marginal_setup(self, prior: MarginalPrior, index: list[int] | None) -> None:
        """Solver columns of the prior's state and a check that its layout matches these terms."""
        K = len(prior.ids)
        if index is None or len(index) != K or not all(0 <= i < self.n for i in index):
            raise ValueError(f"InertialTerms: a MarginalPrior over {K} keyframes needs their window positions "
                             f"(0..{self.n - 1}), got {index}")
        kb = (6 * K if self.per_keyframe_bias else 6) if self.estimate_bias else 0
        if prior.biases.numel() != kb or prior.H.shape != (9 * K + kb, 9 * K + kb):
            raise ValueError(f"InertialTerms: MarginalPrior biases {tuple(prior.biases.shape)} / H "
                             f"{tuple(prior.H.shape)} do not match the terms' bias layout")
        self._marginal_cols = state_columns(index, self.n, self.estimate_bias, self.per_keyframe_bias)
        self._marginal_index = torch.as_tensor(index, dtype=torch.long)

    # ------------------------------------------------------------------ evaluation
    def _check(self, poses: torch.Tensor, state: InertialState) -> None:
        nb = self.n if self.per_keyframe_bias else 1
        if poses.shape != (self.n, 4, 4) or state.velocities.shape != (self.n, 3) or state.biases.shape != (nb, 6):
            raise ValueError(f"InertialTerms over {self.n} keyframes: poses {tuple(poses.shape)}, velocities "
                             f"{tuple(state.velocities.shape)}, biases {tuple(state.biases.shape)}; expected "
                             f"({self.n}, 4, 4), ({self.n}, 3), ({nb}, 6)")

    def _bias_pairs(self, state: InertialState) -> tuple[torch.Tensor, torch.Tensor]:
        b = state.biases
        if self.per_keyframe_bias:
            return b[:-1], b[1:]
        return b.expand(self.n - 1, 6), b.expand(self.n - 1, 6)

    def evaluate(self, poses: torch.Tensor, state: InertialState, jacobians: bool = True) -> InertialResidual:
        """Inertial residuals (n-1, 15) and (``jacobians``) their Jacobians at world->camera ``poses`` (n, 4, 4)
        and ``state``."""
        self._check(poses, state)
        T_wc = se3_inverse(poses.to(torch.float64))
        b_i, b_j = self._bias_pairs(state)
        v = state.velocities
        return inertial_residual(self.pre, T_wc[:-1], v[:-1], b_i, T_wc[1:], v[1:], b_j, state.R_wg,
                                 state.log_scale, self.T_cb, self.gravity, jacobians=jacobians)

    def _residual_vector(self, res: InertialResidual) -> torch.Tensor:
        return res.residual[:, :self.info.shape[-1]]

    def _anchor_residuals(self, state: InertialState):
        """Anchor residuals and their information: velocity (n, 3), (3,); bias (n, 6), (6,)
        (zero rows for unanchored keyframes; bias part zero without per-keyframe bias estimation)."""
        a = self.anchor
        m = a.mask.to(torch.float64)[:, None]
        r_v = m * (state.velocities - a.velocities)
        info_v = torch.full((3,), a.velocity_std ** -2, dtype=torch.float64, device=r_v.device)
        if self.estimate_bias and self.per_keyframe_bias:
            r_b = m * (state.biases - a.biases)
        else:
            r_b = torch.zeros(self.n, 6, dtype=torch.float64, device=r_v.device)
        return r_v, info_v, r_b, a.bias_std.to(r_v) ** -2

    def _prior_cost(self, state: InertialState) -> torch.Tensor:
        cost = torch.zeros((), dtype=torch.float64, device=state.biases.device)
        if self.estimate_bias:
            cost = cost + 0.5 * (self.prior_info * state.biases ** 2).sum()
        if self.anchor is not None:
            r_v, info_v, r_b, info_b = self._anchor_residuals(state)
            cost = cost + 0.5 * ((info_v * r_v ** 2).sum() + (info_b * r_b ** 2).sum())
        return cost

    def _marginal_states(self, poses: torch.Tensor, state: InertialState) -> tuple[torch.Tensor, ...]:
        """Poses, velocities and biases of the marginalisation prior's keyframes."""
        idx = self._marginal_index
        return poses[idx], state.velocities[idx], window_biases(state.biases, idx, self.estimate_bias,
                                                                self.per_keyframe_bias)

    def cost(self, poses: torch.Tensor, state: InertialState) -> torch.Tensor:
        """``1/2 w sum r^T Cov^-1 r`` plus the bias, anchor and marginalisation priors (scalar)."""
        r = self._residual_vector(self.evaluate(poses, state, jacobians=False))
        cost = 0.5 * (r[:, None, :] @ self.info @ r[:, :, None]).sum() + self._prior_cost(state)
        if self.marginal is not None:
            cost = cost + self.marginal.cost(self.marginal.delta(*self._marginal_states(poses, state))[0])
        return cost

    def jacobian(self, poses: torch.Tensor, state: InertialState) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals (n-1, m) and their Jacobian (n-1, m, 6n + dim) in the solver's parameterisation
        (``m`` = 15 with per-keyframe bias estimation, else 9)."""
        res = self.evaluate(poses, state)
        m = self.info.shape[-1]
        B, n, N = self.n - 1, self.n, 6 * self.n + self.dim
        f = dict(dtype=torch.float64, device=poses.device)
        T_wc = se3_inverse(poses.to(torch.float64))
        Ad = se3_adjoint(T_wc)                                              # (n, 6, 6)
        jac = {k: v[:, :m] for k, v in res.jacobians.items()}
        Jt = torch.zeros(B, N, m, **f)                                      # transposed Jacobian
        rows = torch.arange(B, device=poses.device)[:, None]

        def put(col0: torch.Tensor, block: torch.Tensor) -> None:
            cols = col0[:, None] + torch.arange(block.shape[-1], device=poses.device)
            Jt.index_put_((rows.expand_as(cols), cols), block.transpose(-1, -2), accumulate=True)

        k = torch.arange(B, device=poses.device)
        put(6 * k, -jac["pose_i"] @ Ad[:-1])
        put(6 * (k + 1), -jac["pose_j"] @ Ad[1:])
        put(self.off_vel + 3 * k, jac["vel_i"])
        put(self.off_vel + 3 * (k + 1), jac["vel_j"])
        if self.estimate_bias:
            if self.per_keyframe_bias:
                put(self.off_bias + 6 * k, jac["bias_i"])
                put(self.off_bias + 6 * (k + 1), jac["bias_j"])
            else:
                put(torch.full_like(k, self.off_bias), jac["bias_i"] + jac["bias_j"])
        if self.estimate_gravity:
            put(torch.full_like(k, self.off_grav), jac["gravity"])
        if self.estimate_scale:
            put(torch.full_like(k, self.off_scale), jac["log_scale"])
        return self._residual_vector(res), Jt.transpose(-1, -2)

    def linearize(self, poses: torch.Tensor, state: InertialState) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Gauss-Newton ``(H (6n+dim, 6n+dim), g (6n+dim,), cost)`` with ``H dx = g`` (module docstring)."""
        r, J = self.jacobian(poses, state)
        JtW = J.transpose(-1, -2) @ self.info                               # (B, N, m)
        H = (JtW @ J).sum(0)
        g = -(JtW @ r[..., None]).sum(0)[:, 0]
        if self.estimate_bias:
            nb = state.biases.numel()
            sl = slice(self.off_bias, self.off_bias + nb)
            pinfo = self.prior_info.repeat(nb // 6)
            H[sl, sl] += torch.diag(pinfo)
            g[sl] -= pinfo * state.biases.reshape(-1)
        if self.anchor is not None:
            r_v, info_v, r_b, info_b = self._anchor_residuals(state)
            m = self.anchor.mask.to(torch.float64)
            sl = slice(self.off_vel, self.off_vel + 3 * self.n)
            iv = (m[:, None] * info_v).reshape(-1)
            H[sl, sl] += torch.diag(iv)
            g[sl] -= (info_v * r_v).reshape(-1)
            if self.estimate_bias and self.per_keyframe_bias:
                sl = slice(self.off_bias, self.off_bias + 6 * self.n)
                H[sl, sl] += torch.diag((m[:, None] * info_b).reshape(-1))
                g[sl] -= (info_b * r_b).reshape(-1)
        cost = 0.5 * (r[:, None, :] @ self.info @ r[:, :, None]).sum() + self._prior_cost(state)
        if self.marginal is not None:
            Hm, gm, d = self.marginal.linearized(*self._marginal_states(poses, state))
            c = self._marginal_cols
            H[c[:, None], c[None, :]] += Hm
            g[c] += gm
            cost = cost + self.marginal.cost(d)
        return H.to(poses.dtype), g.to(poses.dtype), cost

    def retract(self, state: InertialState, delta: torch.Tensor) -> InertialState:
        """Apply the extra part ``delta (dim,)`` of a step: ``v += dv``, ``b += db``,
        ``R_wg <- R_wg Exp((a, b, 0))``, ``sigma += d``."""
        delta = delta.to(torch.float64)
        o = -6 * self.n
        vel = state.velocities + delta[self.off_vel + o:self.off_bias + o].reshape(self.n, 3)
        biases = state.biases
        if self.estimate_bias:
            biases = biases + delta[self.off_bias + o:self.off_grav + o].reshape(-1, 6)
        R_wg = state.R_wg
        if self.estimate_gravity:
            d = delta[self.off_grav + o:self.off_grav + o + 2]
            R_wg = R_wg @ so3_exp(torch.cat((d, torch.zeros(1, dtype=d.dtype, device=d.device))))
        log_scale = state.log_scale
        if self.estimate_scale:
            log_scale = log_scale + delta[self.off_scale + o]
        return replace(state, velocities=vel, biases=biases, R_wg=R_wg, log_scale=log_scale)
