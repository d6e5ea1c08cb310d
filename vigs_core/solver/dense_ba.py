"""Dense bundle adjustment by Levenberg-Marquardt over keyframe poses and per-pixel inverse depth.

Minimises ``sum_(i,j) sum_p conf_ijp * rho(|u*_ijp - pi(T_j T_i^-1, d_ip, p)|)`` (VIGS-SLAM Eq. 3-4, DROID-SLAM
Eq. 3) with Huber ``rho`` by IRLS. Each iteration linearises, eliminates the disparities by the Schur
complement (:mod:`vigs_core.solver.normal_equations`), adds the contributions of any
:class:`AdditionalTerms` (e.g. inertial residuals over velocities and biases appended after the poses), damps the
diagonal (LM, Marquardt 1963: ``H + lambda diag(H)``), solves by Cholesky, back-substitutes the disparities and
accepts the step only if the total cost decreases.

Gauge: the poses flagged ``fixed`` are held; a monocular problem needs at least one fixed pose (rotation and
translation gauge); its scale gauge is fixed by a second fixed pose, by holding the disparities of a fixed
keyframe (``fixed_disparity``), or left to the LM damping. Two fixed poses with a tiny or noisy baseline pin
a wrong scale ratio and pull the map's scale away; the frontend fixes one keyframe, with its depth when
``OdometryConfig.hold_fixed_disparity`` is set.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch

from vigs_core.geometry import se3_exp
from vigs_core.ranges import bounded
from vigs_core.solver.normal_equations import (EdgeSet, back_substitute, linearize_visual, schur_reduce,
                                               visual_cost)
from vigs_core.solver.projective import Intrinsics


@dataclass
class BAConfig:
    """Settings of dense BA.

    Args:
        iterations: maximum LM iterations per call.
        huber_delta: Huber threshold on the reprojection residual norm, pixels (input resolution).
        lm_lambda: initial LM damping factor (multiplies the diagonal).
        lm_lambda_min, lm_lambda_max: bounds of the damping factor; an iteration that cannot reduce the cost
            with lambda at its maximum ends the solve.
        disparity_damping: added to the disparity diagonal (keeps unobserved pixels at their value), 1/m^2.
        min_disparity: lower bound of inverse depth after each update, 1/m (keeps points in front).
        rel_tol: stop when the relative cost decrease of an accepted step falls below this.
    """

    iterations: int = bounded(8, 0)
    huber_delta: float = bounded(2.0, 0, lo_open=True)
    lm_lambda: float = bounded(1e-4, 0, lo_open=True)
    lm_lambda_min: float = bounded(1e-10, 0, lo_open=True)
    lm_lambda_max: float = bounded(1e6, 0, lo_open=True)
    disparity_damping: float = bounded(1e-6, 0)
    min_disparity: float = bounded(1e-4, 0, lo_open=True)
    rel_tol: float = bounded(1e-12, 0)


class AdditionalTerms(Protocol):
    """Residuals over the poses plus ``dim`` extra states, added to the reduced camera system.

    The full reduced state is ``[xi_0 .. xi_{n-1}, extra]`` (6n + dim). ``state`` is whatever the provider
    needs for its extra variables (velocities, biases, ...); the solver only passes it around.
    """

    dim: int

    def linearize(self, poses: torch.Tensor, state: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(H (6n+dim, 6n+dim), g (6n+dim,), cost)`` with ``H dx = g`` the Gauss-Newton step."""

    def cost(self, poses: torch.Tensor, state: Any) -> torch.Tensor:
        """The terms' cost at ``(poses, state)`` (same scale as ``0.5 r^T W r``)."""

    def retract(self, state: Any, delta: torch.Tensor) -> Any:
        """New state after the extra part ``delta (dim,)`` of the step."""


@dataclass
class BAResult:
    """Outcome of :func:`bundle_adjust`: ``poses (n, 4, 4)``, ``disps (n, P)``, the extra state, the cost after
    each accepted iteration (``costs[0]`` is the initial cost) and the number of iterations run."""

    poses: torch.Tensor
    disps: torch.Tensor
    extra_state: Any = None
    costs: list[float] = field(default_factory=list)
    iterations: int = 0


def _solve_spd(H: torch.Tensor, g: torch.Tensor) -> torch.Tensor | None:
    L, info = torch.linalg.cholesky_ex(H)
    if int(info) != 0:
        return None
    return torch.cholesky_solve(g[:, None], L)[:, 0]


def bundle_adjust(poses: torch.Tensor, disps: torch.Tensor, edges: EdgeSet, coords: torch.Tensor,
                  intr: Intrinsics, fixed: torch.Tensor, config: BAConfig | None = None,
                  extra: AdditionalTerms | None = None, extra_state: Any = None,
                  fixed_disparity: torch.Tensor | None = None, visual_dtype: torch.dtype | None = None,
                  between: Callable[[], None] | None = None) -> BAResult:
    """Levenberg-Marquardt dense BA (see the module docstring).

    Args:
        poses: (n, 4, 4) world->camera keyframe poses (initial estimate).
        disps: (n, P) inverse depths of each keyframe's grid pixels ``coords`` (P, 2).
        edges: correspondences between keyframes (indices into ``poses``).
        intr: intrinsics of the coordinates' image.
        fixed: (n,) bool, poses held constant (gauge).
        extra: optional additional residual terms over the poses and extra states.
        fixed_disparity: (n,) bool, keyframes whose disparities are held constant (a fixed keyframe with
            fixed disparities pins the monocular scale through its depth map); None holds none.
        visual_dtype: dtype of the visual linearisation, Schur complement, back-substitution and cost (e.g.
            float32, about 1.5x faster on CPU); the reduced camera system, the additional terms and the
            returned state keep the dtype of ``poses``. None: that of ``poses``.
        between: called after each linearisation and before each iteration after the first (a live caller
            tracks a frame that arrived meanwhile; it must not change the inputs).
    Returns:
        :class:`BAResult` with the optimised poses and disparities.
    """
    cfg = config or BAConfig()
    n, P = disps.shape
    if poses.shape != (n, 4, 4) or coords.shape != (P, 2) or fixed.shape != (n,):
        raise ValueError(f"bundle_adjust: poses {tuple(poses.shape)}, disps {tuple(disps.shape)}, coords "
                         f"{tuple(coords.shape)}, fixed {tuple(fixed.shape)}; expected (n,4,4), (n,P), (P,2), (n,)")
    m = extra.dim if extra is not None else 0
    free = torch.cat((~fixed[:, None].expand(n, 6).reshape(-1),
                      torch.ones(m, dtype=torch.bool, device=poses.device)))
    lam = cfg.lm_lambda
    vd = poses.dtype if visual_dtype is None else visual_dtype
    v_edges = EdgeSet(edges.ii, edges.jj, edges.target.to(vd), edges.weight.to(vd))
    v_coords = coords.to(vd)

    def total_cost(T, d, st):
        c = float(visual_cost(T.to(vd), d.to(vd), v_edges, v_coords, intr, cfg.huber_delta))
        return c + float(extra.cost(T, st)) if extra is not None else c

    result = BAResult(poses, disps, extra_state)
    cost0 = None
    for it in range(cfg.iterations):
        if it and between is not None:
            between()
        system = linearize_visual(result.poses.to(vd), result.disps.to(vd), v_edges, v_coords, intr,
                                  cfg.huber_delta)
        if cost0 is None:   # the starting cost: the first linearisation sums the same robust cost
            cost0 = float(system.cost) + (float(extra.cost(poses, extra_state)) if extra is not None else 0.0)
            result.costs.append(cost0)
        if fixed_disparity is not None:
            system.freeze_disparities(fixed_disparity)
        if extra is not None:
            H_x, g_x, _ = extra.linearize(result.poses, result.extra_state)
        if between is not None:
            between()
        accepted = False
        while not accepted and lam <= cfg.lm_lambda_max:
            C_d = system.C * (1.0 + lam) + cfg.disparity_damping
            S, s = (x.to(poses.dtype) for x in schur_reduce(system, C_d))
            B_diag = torch.diagonal(system.B, dim1=2, dim2=3).diagonal(dim1=0, dim2=1).T.reshape(-1)  # (6n,)
            B_diag = B_diag.to(poses.dtype)
            H = torch.zeros(6 * n + m, 6 * n + m, dtype=poses.dtype, device=poses.device)
            g = torch.zeros(6 * n + m, dtype=poses.dtype, device=poses.device)
            H[:6 * n, :6 * n] = S + torch.diag(lam * B_diag)
            g[:6 * n] = s
            if extra is not None:
                H = H + H_x + torch.diag(lam * torch.diagonal(H_x))
                g = g + g_x
            Hf = H[free][:, free]
            top = float(Hf.diagonal().max()) if Hf.numel() else 0.0   # all poses fixed: disparities only
            Hf = Hf + torch.eye(Hf.shape[0], dtype=H.dtype, device=H.device) * 1e-9 * (1.0 + top)
            dx_f = _solve_spd(Hf, g[free])
            if dx_f is None:
                lam = max(lam * 10.0, 1e-6)
                continue
            dx = torch.zeros(6 * n + m, dtype=H.dtype, device=H.device)
            dx[free] = dx_f
            dxi = dx[:6 * n].view(n, 6)
            dd = back_substitute(system, C_d, dxi.to(vd)).to(disps.dtype)
            T_new = se3_exp(dxi) @ result.poses
            d_new = (result.disps + dd).clamp(min=cfg.min_disparity)
            st_new = extra.retract(result.extra_state, dx[6 * n:]) if extra is not None else None
            cost1 = total_cost(T_new, d_new, st_new)
            if cost1 <= cost0:
                accepted = True
                rel = (cost0 - cost1) / max(cost0, 1e-300)
                result.poses, result.disps, result.extra_state = T_new, d_new, st_new
                cost0 = cost1
                result.costs.append(cost1)
                lam = max(lam / 3.0, cfg.lm_lambda_min)
            else:
                lam *= 4.0
        result.iterations = it + 1
        if not accepted or rel < cfg.rel_tol:
            break
    return result
