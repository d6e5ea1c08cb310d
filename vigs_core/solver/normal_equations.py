"""Normal equations of dense bundle adjustment and their Schur complement (VIGS-SLAM Eq. 4, DROID-SLAM 3.3).

Unknowns: keyframe poses ``xi`` (6 per keyframe, left perturbations of world->camera poses) and one inverse
depth per keyframe pixel ``d``. With weighted residuals ``r = u* - pi(T_ji, d)`` and Jacobians ``J = d pi / dx``
the Gauss-Newton system is

    [ B    E ] [dxi]   [v]
    [ E^T  C ] [dd ] = [w]       B = J_xi^T W J_xi, E = J_xi^T W J_d, C = diag(J_d^T W J_d),
                                 v = J_xi^T W r, w = J_d^T W r.

``C`` is diagonal because each residual involves exactly one disparity, so the disparities are eliminated
cheaply: ``(B - E C^-1 E^T) dxi = v - E C^-1 w`` (the reduced camera system), then
``dd = C^-1 (w - E^T dxi)``.

``E`` is stored sparsely, as "blocks": one (6, P) matrix per (pose, source keyframe) pair that shares
disparities. For a source keyframe ``i`` these are ``i`` itself (the sum over all edges leaving ``i``) and each
target ``j`` of an edge ``(i, j)``. The Schur product ``E C^-1 E^T`` is then a sum over pairs of blocks with the
same source, so its cost grows with the number of edges, not with the square of the window.

The reduced system is a dense (6n, 6n) matrix over the poses in keyframe order; extra Hessian and gradient
contributions from other residuals (e.g. inertial terms) are added to it before it is solved (see
:class:`vigs_core.solver.dense_ba.AdditionalTerms`).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from vigs_core.compiled import numba_available
from vigs_core.geometry import se3_adjoint, se3_inverse
from vigs_core.solver.projective import Intrinsics, reproject
from vigs_core.solver.robust import huber_cost, huber_weight


@dataclass
class EdgeSet:
    """Correspondences of a frame graph: for each edge ``(ii[e], jj[e])`` the measured target coordinates of
    the source keyframe's grid pixels in the target keyframe and their confidences.

    ``ii, jj`` (E,) long keyframe indices into the solver's pose array; ``target`` (E, P, 2) pixels;
    ``weight`` (E, P) or (E, P, 2) confidences in [0, 1] (per axis when (E, P, 2)).
    """

    ii: torch.Tensor
    jj: torch.Tensor
    target: torch.Tensor
    weight: torch.Tensor

    def __post_init__(self) -> None:
        n = self.ii.shape[0]
        if self.jj.shape != (n,) or self.target.shape[0] != n or self.weight.shape[0] != n:
            raise ValueError(f"EdgeSet: ii {tuple(self.ii.shape)}, jj {tuple(self.jj.shape)}, target "
                             f"{tuple(self.target.shape)}, weight {tuple(self.weight.shape)} must share E")
        if bool((self.ii == self.jj).any()):
            raise ValueError("EdgeSet: an edge connects a keyframe to itself; expected ii != jj")

    def pixel_weight(self) -> torch.Tensor:
        """Weights as (E, P, 2)."""
        return self.weight if self.weight.dim() == 3 else self.weight[..., None].expand(-1, -1, 2)


@dataclass
class VisualSystem:
    """Linearised visual terms (see the module docstring for the symbols).

    ``B (n, n, 6, 6)``, ``v (n, 6)``, ``C (n, P)``, ``w (n, P)``. E blocks grouped by source keyframe:
    ``src (s,)`` the keyframes that own disparities with observations, ``block_pose (s, K)`` the pose index of
    each block (-1 for padding), ``block_E (s, K, 6, P)`` (pixels last: the Schur products' layout); block 0 of a
    source is its own pose. ``cost``
    (scalar, ``sum conf * rho(|r|)``), ``residual (E, P, 2)`` and ``valid (E, P)``.
    """

    B: torch.Tensor
    v: torch.Tensor
    C: torch.Tensor
    w: torch.Tensor
    src: torch.Tensor
    block_pose: torch.Tensor
    block_E: torch.Tensor
    cost: torch.Tensor
    residual: torch.Tensor
    valid: torch.Tensor

    def freeze_disparities(self, frozen: torch.Tensor) -> None:
        """Hold the disparities of keyframes ``frozen`` (n,) bool constant: their coupling to the poses is
        removed (``E = 0``, ``w = 0``) so the Schur complement leaves ``B`` as the fixed-depth information."""
        keep = ~frozen[self.src]
        self.block_E = self.block_E * keep[:, None, None, None]
        self.w = self.w * ~frozen[:, None]


def residuals(poses: torch.Tensor, disps: torch.Tensor, edges: EdgeSet, coords: torch.Tensor,
              intr: Intrinsics, jacobians: bool = False):
    """Residuals ``u* - pi`` (E, P, 2) and the :class:`Reprojection` they came from (with ``jacobians``:
    ``J_j``, ``J_d`` and ``Ad``, not the per-pixel ``J_i``)."""
    proj = reproject(poses[edges.ii], poses[edges.jj], disps[edges.ii], coords, intr, jacobians,
                     source_jacobian=False)
    return edges.target - proj.uv, proj


def _kernels(compiled: bool, poses: torch.Tensor):
    """The compiled kernels (:mod:`vigs_core.solver.linearize_numba`) where they apply: ``compiled`` asked for, CPU
    tensors, numba installed; else None (the tensor operations)."""
    if compiled and poses.device.type == "cpu" and numba_available():
        from vigs_core.solver import linearize_numba
        return linearize_numba
    return None


def visual_cost(poses: torch.Tensor, disps: torch.Tensor, edges: EdgeSet, coords: torch.Tensor,
                intr: Intrinsics, huber_delta: float, compiled: bool = True) -> torch.Tensor:
    """Robust cost ``sum_e sum_p conf * rho(|r|)`` (scalar) over valid projections (``compiled``: as
    :func:`linearize_visual`)."""
    if (kernels := _kernels(compiled, poses)) is not None:
        T_ji = poses[edges.jj] @ se3_inverse(poses[edges.ii])
        return kernels.edge_cost(T_ji, disps[edges.ii], coords, edges.target, edges.pixel_weight(), intr, huber_delta)
    r, proj = residuals(poses, disps, edges, coords, intr)
    conf = edges.pixel_weight().mean(-1) * proj.valid
    return (conf * huber_cost(r.norm(dim=-1), huber_delta)).sum()


def linearize_visual(poses: torch.Tensor, disps: torch.Tensor, edges: EdgeSet, coords: torch.Tensor,
                     intr: Intrinsics, huber_delta: float, compiled: bool = True) -> VisualSystem:
    """Build ``B, E, C, v, w`` at the current estimate with IRLS Huber weights (threshold in pixels).

    Args:
        poses: (n, 4, 4) world->camera; disps: (n, P); coords: (P, 2) pixel coordinates of the grid.
        compiled: on CPU with numba installed, the per-pixel terms and their sums come from one compiled loop
            (:mod:`vigs_core.solver.linearize_numba`) instead of tensor operations (:func:`_edge_terms`).
    """
    n, P = disps.shape
    ii, jj = edges.ii, edges.jj
    ne = ii.shape[0]
    src, group = torch.unique(ii, return_inverse=True)                       # group: edge -> source slot
    order = torch.argsort(group, stable=True)
    counts = torch.bincount(group, minlength=src.shape[0])
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.empty_like(group)
    rank[order] = torch.arange(ne, device=ii.device) - starts[group[order]]
    K = 1 + int(counts.max())
    if (kernels := _kernels(compiled, poses)) is not None:
        T_ji = poses[jj] @ se3_inverse(poses[ii])
        Ad = se3_adjoint(T_ji)
        Hjj, vj, C, w, block_E, r, valid, cost = kernels.linearize_edges(
            T_ji, Ad, disps[ii], coords, edges.target, edges.pixel_weight(), intr, huber_delta, ii, group, rank, n,
            src.shape[0], K)
    else:
        Hjj, vj, Ce, we, Ej, r, valid, cost, Ad = _edge_terms(poses, disps, edges, coords, intr, huber_delta)
        C = torch.zeros(n, P, dtype=poses.dtype, device=poses.device)
        w = torch.zeros(n, P, dtype=poses.dtype, device=poses.device)
        C.index_add_(0, ii, Ce)
        w.index_add_(0, ii, we)
        block_E = torch.zeros(src.shape[0], K, 6, P, dtype=poses.dtype, device=poses.device)
        block_E[:, 0].index_add_(0, group, -(Ej @ Ad).transpose(1, 2))     # the source's E_i = -E_j Ad
        block_E[group, rank + 1] = Ej.transpose(1, 2)
    # J_i = -J_j Ad (projective.py), so the source blocks follow from the target ones by 6x6 products:
    # J_i^T W J_i = Ad^T H_jj Ad, J_i^T W J_j = -Ad^T H_jj, J_i^T W r = -Ad^T J_j^T W r
    AdT = Ad.transpose(1, 2)
    Hij = -(AdT @ Hjj)
    Hii = -(Hij @ Ad)
    B = torch.zeros(n * n, 6, 6, dtype=poses.dtype, device=poses.device)
    B.index_add_(0, ii * n + ii, Hii)
    B.index_add_(0, ii * n + jj, Hij)
    B.index_add_(0, jj * n + ii, Hij.transpose(1, 2))
    B.index_add_(0, jj * n + jj, Hjj)
    v = torch.zeros(n, 6, dtype=poses.dtype, device=poses.device)
    v.index_add_(0, ii, -(AdT @ vj[..., None])[..., 0])
    v.index_add_(0, jj, vj)
    block_pose = torch.full((src.shape[0], K), -1, dtype=torch.long, device=ii.device)
    block_pose[:, 0] = src
    block_pose[group, rank + 1] = jj
    return VisualSystem(B.view(n, n, 6, 6), v, C, w, src, block_pose, block_E, cost, r, valid)


def _edge_terms(poses: torch.Tensor, disps: torch.Tensor, edges: EdgeSet, coords: torch.Tensor, intr: Intrinsics,
                huber_delta: float) -> tuple:
    """Per-edge terms of :func:`linearize_visual` with tensor operations: ``H_jj`` (E, 6, 6), ``v_j`` (E, 6), the
    per-pixel ``C`` and ``w`` contributions (E, P), the target's E block rows ``E_j`` (E, P, 6), residual (E, P,
    2), valid (E, P), the cost and the adjoints ``Ad`` (E, 6, 6) of the relative poses."""
    ne, P = edges.ii.shape[0], disps.shape[1]
    r, proj = residuals(poses, disps, edges, coords, intr, jacobians=True)
    rnorm = r.norm(dim=-1)
    wr = huber_weight(rnorm, huber_delta) * proj.valid                       # (E, P)
    W = edges.pixel_weight() * wr[..., None]                                # (E, P, 2)
    cost = (edges.pixel_weight().mean(-1) * proj.valid * huber_cost(rnorm, huber_delta)).sum()
    Jj = proj.J_j.reshape(ne, 2 * P, 6)
    WJjT = (W.reshape(ne, 2 * P, 1) * Jj).transpose(1, 2)                   # (E, 6, 2P)
    Hjj = WJjT @ Jj                                                          # (E, 6, 6)
    vj = (WJjT @ r.reshape(ne, 2 * P, 1))[..., 0]                            # (E, 6)
    Jd = proj.J_d                                                            # (E, P, 2)
    WJd = W * Jd
    Ce = WJd[..., 0] * Jd[..., 0] + WJd[..., 1] * Jd[..., 1]
    we = WJd[..., 0] * r[..., 0] + WJd[..., 1] * r[..., 1]
    # E block rows (6,) per pixel = sum over its 2 rows of J_pose^T W J_d
    Ej = WJd[..., 0:1] * proj.J_j[..., 0, :] + WJd[..., 1:2] * proj.J_j[..., 1, :]   # (E, P, 6)
    return Hjj, vj, Ce, we, Ej, r, proj.valid, cost, proj.Ad


def schur_reduce(system: VisualSystem, C_damped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Reduced camera system ``S = B - E C^-1 E^T`` (6n, 6n) and ``s = v - E C^-1 w`` (6n,).

    ``C_damped`` (n, P) is the (damped, strictly positive) disparity diagonal to eliminate with. Per source
    keyframe the (6K, P) stack ``M`` of its blocks gives ``M C^-1 M^T`` in one batched product.
    """
    n = system.B.shape[0]
    ns, K, _, P = system.block_E.shape
    inv_C = (1.0 / C_damped)[system.src]                                      # (s, P)
    M = system.block_E.reshape(ns, 6 * K, P)
    Q = (M * inv_C[:, None, :]) @ M.transpose(1, 2)                            # (s, 6K, 6K)
    Q = Q.view(ns, K, 6, K, 6).permute(0, 1, 3, 2, 4)                         # (s, K, K, 6, 6)
    pa = system.block_pose[:, :, None].expand(ns, K, K)
    pb = system.block_pose[:, None, :].expand(ns, K, K)
    ok = (pa >= 0) & (pb >= 0)
    S = system.B.reshape(n * n, 6, 6).clone()
    S.index_add_(0, pa[ok] * n + pb[ok], -Q[ok])
    S = S.view(n, n, 6, 6).permute(0, 2, 1, 3).reshape(6 * n, 6 * n)
    q = (M @ (system.w[system.src] * inv_C)[..., None]).view(ns, K, 6)      # (s, K, 6)
    valid = system.block_pose >= 0
    s = system.v.clone()
    s.index_add_(0, system.block_pose[valid], -q[valid])
    return S, s.reshape(6 * n)


def back_substitute(system: VisualSystem, C_damped: torch.Tensor, dxi: torch.Tensor) -> torch.Tensor:
    """Disparity update ``dd = C^-1 (w - E^T dxi)`` (n, P) from the pose update ``dxi`` (n, 6)."""
    bp = system.block_pose
    dx_blocks = torch.where((bp >= 0)[..., None], dxi[bp.clamp(min=0)], torch.zeros_like(dxi[:1]))  # (s, K, 6)
    Etx = torch.einsum("skxp,skx->sp", system.block_E, dx_blocks)
    rhs = system.w.clone()
    rhs.index_add_(0, system.src, -Etx)
    return rhs / C_damped
