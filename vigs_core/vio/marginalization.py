"""Marginalising the oldest keyframe of the sliding window into a Gaussian prior on the states that remain.

When keyframe ``k_0`` leaves the window ``U = (k_0, k_1, .., k_{N-1})`` (consecutive keyframes), the factors
that involve its state ``x_m = (xi_0, v_0, b_0)`` are linearised at the current estimate and summed into one
Gauss-Newton system over the states of ``U`` (layout of :class:`~vigs_core.vio.inertial_terms.InertialTerms`
over ``N`` keyframes, ``H dx = g``):

* the previous marginalisation prior (:class:`~vigs_core.vio.inertial_terms.MarginalPrior`), moved to the
  current estimate: ``A^T H_p A``, ``A^T (g_p - H_p delta)``;
* the inertial factor ``(k_0, k_1)`` (VIGS-SLAM Eq. (2)-(3)) and the zero-mean prior of ``b_0``;
* the visual edges hosted by ``k_0`` with ``k_0``'s disparities eliminated (Schur complement, the reduced
  camera system of :func:`vigs_core.solver.normal_equations.schur_reduce`), passed in by the caller. Edges
  hosted by the remaining keyframes and observed in ``k_0`` are dropped (their disparities stay states, so
  keeping them would couple the prior to whole depth maps; as in DSO, Engel et al. 2018, Sec. 2.3).

Partitioning ``x = (x_m, x_r)``, the Schur complement (e.g. Leutenegger et al. 2015, OKVIS, Eq. (26))

    H_p' = H_rr - H_rm H_mm^-1 H_mr,        g_p' = g_r - H_rm H_mm^-1 g_m

is the information that ``k_0``'s factors leave on ``x_r``: the prior of the next windows, linearised at this
estimate (first-estimate Jacobians). It replaces holding the oldest keyframe fixed: the window keeps the scale
and velocity information of the keyframes that left it instead of copying one keyframe's velocity.

The first marginalisation after the map became metric has no prior yet: ``k_0`` was the fixed keyframe of the
window, so its pose is conditioned on (held, its columns dropped: the prior then carries the gauge) and its
velocity and bias get the anchor prior (``anchor_std``, none when its velocity std is 0) before they are
eliminated.
"""
from __future__ import annotations

import torch

from vigs_core.imu.preintegration import Preintegrated
from vigs_core.vio.inertial_terms import InertialState, InertialTerms, MarginalPrior, state_columns, window_biases

F64 = torch.float64


def _pinv_psd(H: torch.Tensor) -> torch.Tensor:
    """Pseudo-inverse of a symmetric positive semi-definite matrix (eigenvalues below 1e-12 of the largest
    treated as zero)."""
    lam, V = torch.linalg.eigh(0.5 * (H + H.T))
    keep = lam > 1e-12 * max(float(lam.max()), 1e-300)
    inv = torch.where(keep, 1.0 / torch.where(keep, lam, torch.ones_like(lam)), torch.zeros_like(lam))
    return (V * inv) @ V.T


def marginalize_keyframe(prior: MarginalPrior | None, ids: list[int], poses: torch.Tensor,
                         velocities: torch.Tensor, biases: torch.Tensor, pre: Preintegrated, T_cb: torch.Tensor, *,
                         estimate_bias: bool, per_keyframe_bias: bool, gravity: float, weight: float,
                         bias_prior_std: torch.Tensor, visual: tuple[torch.Tensor, torch.Tensor] | None = None,
                         anchor_std: tuple[float, torch.Tensor] | None = None) -> MarginalPrior:
    """Marginalise ``ids[0]`` out of the window ``ids`` (module docstring).

    Args:
        prior: the current prior (its keyframes must be in ``ids``), or None for the first marginalisation
            (``ids[0]``'s pose is then conditioned on and ``anchor_std`` must be given).
        ids: the window's ``N >= 2`` keyframe ids, consecutive, oldest (the one to marginalise) first.
        poses: (N, 4, 4) world->camera; velocities (N, 3); biases (N, 6) per keyframe or (1, 6) global (held
            values when not estimated): the current estimate (the new linearisation point).
        pre: batched preintegration (1 interval) from ``ids[0]`` to ``ids[1]`` at ``ids[0]``'s bias.
        T_cb: (4, 4) body->camera extrinsic; estimate_bias, per_keyframe_bias, gravity, weight: as
            :class:`InertialTerms`; bias_prior_std: (6,) the zero-mean bias prior (applied to ``b_0`` here).
        visual: optional reduced camera system ``(S (6N, 6N), s (6N,))`` of the edges hosted by ``ids[0]``.
        anchor_std: (velocity std m/s, bias stds (6,)) of the first marginalisation's anchor prior.
    Returns:
        The prior over ``ids[1:]``.
    """
    N = len(ids)
    if N < 2 or poses.shape != (N, 4, 4) or velocities.shape != (N, 3):
        raise ValueError(f"marginalize_keyframe: ids {ids}, poses {tuple(poses.shape)}, velocities "
                         f"{tuple(velocities.shape)}; expected N >= 2 keyframes with (N, 4, 4) and (N, 3)")
    if prior is None and anchor_std is None:
        raise ValueError("marginalize_keyframe: the first marginalisation needs anchor_std")
    poses, velocities, biases = poses.to(F64), velocities.to(F64), biases.to(F64)
    nb = (6 * N if per_keyframe_bias else 6) if estimate_bias else 0
    D = 9 * N + nb
    H = torch.zeros(D, D, dtype=F64)
    g = torch.zeros(D, dtype=F64)

    if prior is not None:
        if not set(prior.ids) <= set(ids):
            raise ValueError(f"marginalize_keyframe: prior keyframes {prior.ids} not in the window {ids}")
        pos = [ids.index(k) for k in prior.ids]
        Hp, gp, _ = prior.linearized(poses[pos], velocities[pos],
                                     window_biases(biases, pos, estimate_bias, per_keyframe_bias))
        c = state_columns(pos, N, estimate_bias, per_keyframe_bias)
        H[c[:, None], c[None, :]] += Hp
        g[c] += gp

    # inertial factor (k_0, k_1); the bias prior of b_1 stays with the windows that still hold k_1
    terms = InertialTerms(pre, T_cb, estimate_bias=estimate_bias, per_keyframe_bias=per_keyframe_bias,
                          gravity=gravity, weight=weight, bias_prior_std=torch.full((6,), 1e12, dtype=F64))
    state = InertialState(velocities[:2], biases[:2] if per_keyframe_bias else biases, torch.eye(3, dtype=F64),
                          torch.zeros((), dtype=F64))
    H2, g2, _ = terms.linearize(poses[:2], state)
    c = state_columns([0, 1], N, estimate_bias, per_keyframe_bias)
    H[c[:, None], c[None, :]] += H2.to(F64)
    g[c] += g2.to(F64)
    if estimate_bias and per_keyframe_bias:
        info = bias_prior_std.to(F64) ** -2
        b0 = 9 * N + torch.arange(6)
        H[b0, b0] += info
        g[b0] -= info * biases[0]

    if visual is not None:
        S, s = visual
        H[:6 * N, :6 * N] += S.to(F64)
        g[:6 * N] += s.to(F64)

    cols0 = state_columns([0], N, estimate_bias, per_keyframe_bias)
    own = cols0[:9] if not (estimate_bias and per_keyframe_bias) else cols0   # a global bias is not k_0's
    if prior is None:
        std_v, std_b = anchor_std
        if std_v > 0:
            H[own[6:9], own[6:9]] += std_v ** -2
            if estimate_bias and per_keyframe_bias:
                H[own[9:], own[9:]] += std_b.to(F64) ** -2
        m = own[6:]    # the pose is conditioned on: its columns are left out, passing no information on
    else:
        m = own
    drop = torch.zeros(D, dtype=torch.bool)
    drop[own] = True
    r = torch.nonzero(~drop)[:, 0]
    Hmm_inv = _pinv_psd(H[m[:, None], m[None, :]])
    H_rm = H[r[:, None], m[None, :]]
    H_new = H[r[:, None], r[None, :]] - H_rm @ Hmm_inv @ H_rm.T
    g_new = g[r] - H_rm @ (Hmm_inv @ g[m])
    H_new = 0.5 * (H_new + H_new.T)
    c0 = float(0.5 * g_new @ (_pinv_psd(H_new) @ g_new))
    keep = list(range(1, N))
    return MarginalPrior(list(ids[1:]), poses[1:].clone(), velocities[1:].clone(),
                         window_biases(biases, keep, estimate_bias, per_keyframe_bias).clone(), H_new, g_new, c0)
