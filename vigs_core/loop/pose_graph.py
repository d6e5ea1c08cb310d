"""Sim(3) pose-graph optimisation (the relative-pose part of VIGS-SLAM's PGBA, Sec. 3.1).

Nodes are keyframe similarities ``S_i = T_WC_i`` (world from camera, with a per-keyframe scale so scale
drift can be corrected). An edge ``(i, j)`` measures the relative similarity ``Z_ij ~ S_i^{-1} S_j``
with a 7x7 information matrix ``Lambda_ij`` (tangent order ``(rho, phi, sigma)``). The cost is

    E = sum_ij  rho_h( r_ij^T Lambda_ij r_ij ),   r_ij = Log(Z_ij^{-1} S_i^{-1} S_j)   (in R^7)

with an optional Huber ``rho_h`` on loop edges, plus optional absolute priors on node scales,
``sum_k lambda_k (log s_k)^2`` (``s_k`` the scale of ``S_k``: nodes whose scale is observed, e.g. by an IMU, and
so should not absorb a loop's scale; ``d log s_k / d d_k = e_7``) and on node gravity directions,
``sum_k mu_k |R_k^T e_z - R0_k^T e_z|^2`` (``R0_k`` the node's rotation before the optimisation: roll and pitch
observed by an IMU stay, yaw is free as in VINS-Mono's 4-DoF loop graph; with ``R_k <- Exp(phi) R_k`` the
derivative is ``R_k^T [e_z]_x`` on ``phi``). With left perturbations ``S_k <- Exp(d_k) S_k`` and
``E_ij = Z_ij^{-1} S_i^{-1} S_j``:

    d r_ij / d d_j =  J_l^{-1}(r_ij) Ad((S_i Z_ij)^{-1}),     d r_ij / d d_i = -d r_ij / d d_j

(because ``Z^{-1} S_i^{-1} Exp(d) S_j = Exp(Ad_{(S_i Z)^{-1}} d) E``). Levenberg-Marquardt on the sparse
7N x 7N normal equations (a chain of odometry edges plus a few loop edges: nearly banded, so a sparse LU
(SciPy's SuperLU with a fill-reducing ordering) solves hundreds of keyframes in milliseconds where a dense
factorisation takes seconds); fixed nodes (the gauge) are removed from the system.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from vigs_core.geometry import hat, sim3_adjoint, sim3_exp, sim3_inverse, sim3_left_jacobian_inv, sim3_log
from vigs_core.ranges import bounded


@dataclass
class PoseGraphConfig:
    """Settings of :func:`optimize_pose_graph`.

    Args:
        max_iterations: LM iterations at most.
        initial_damping: LM damping ``lambda`` added as ``lambda * diag(H)`` (Marquardt scaling).
        huber_delta: Huber threshold on the whitened residual norm of edges marked robust; ``0`` disables.
        tolerance: stop when the relative cost decrease falls below this.
    """

    max_iterations: int = bounded(30, 0)
    initial_damping: float = bounded(1e-4, 0, lo_open=True)
    huber_delta: float = bounded(3.0, 0)
    tolerance: float = bounded(1e-10, 0)


@dataclass
class PoseGraph:
    """A Sim(3) pose graph.

    Attributes:
        poses: (N, 4, 4) float64 node similarities ``S_i``.
        edges_i, edges_j: (E,) int64 node indices of each edge.
        measurements: (E, 4, 4) relative similarities ``Z_ij``.
        information: (E, 7, 7) information matrices ``Lambda_ij``.
        robust: (E,) bool, edges whose cost gets the Huber kernel (loop edges).
        fixed: node indices held constant (at least one, to fix the gauge).
        scale_information: (N,) information ``lambda_k`` of the prior ``log s_k = 0`` on each node's scale
            (0: no prior; None: none at all).
        gravity_information: (N,) information ``mu_k`` (1/rad^2) of the prior holding each node's gravity direction
            (roll and pitch) where it is (0: no prior; None: none at all).
    """

    poses: torch.Tensor
    edges_i: torch.Tensor
    edges_j: torch.Tensor
    measurements: torch.Tensor
    information: torch.Tensor
    robust: torch.Tensor | None = None
    fixed: list[int] = field(default_factory=lambda: [0])
    scale_information: torch.Tensor | None = None
    gravity_information: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n, e = self.poses.shape[0], self.edges_i.shape[0]
        if self.poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must be (N, 4, 4), got {tuple(self.poses.shape)}")
        for name, t, shape in (
            ("edges_j", self.edges_j, (e,)),
            ("measurements", self.measurements, (e, 4, 4)),
            ("information", self.information, (e, 7, 7)),
        ):
            if tuple(t.shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
        if e and (min(self.edges_i.min(), self.edges_j.min()) < 0 or max(self.edges_i.max(), self.edges_j.max()) >= n):
            raise ValueError(f"edge indices must lie in [0, {n})")
        if not self.fixed:
            raise ValueError("at least one node must be fixed to remove the Sim(3) gauge freedom")
        if self.robust is None:
            self.robust = torch.zeros(e, dtype=torch.bool)
        for name in ("scale_information", "gravity_information"):
            value = getattr(self, name)
            if value is not None and tuple(value.shape) != (n,):
                raise ValueError(f"{name} must have shape {(n,)}, got {tuple(value.shape)}")

    @staticmethod
    def relative(poses: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """Relative similarities ``S_i^{-1} S_j`` (E, 4, 4) of node pairs."""
        return sim3_inverse(poses[i]) @ poses[j]


@dataclass
class PoseGraphResult:
    """Outcome of :func:`optimize_pose_graph`: optimised poses and the cost history."""

    poses: torch.Tensor
    initial_cost: float
    final_cost: float
    iterations: int
    costs: list[float]


def _residuals(graph: PoseGraph, poses: torch.Tensor) -> torch.Tensor:
    err = sim3_inverse(graph.measurements) @ PoseGraph.relative(poses, graph.edges_i, graph.edges_j)
    return sim3_log(err)


def _log_scales(poses: torch.Tensor) -> torch.Tensor:
    """``log s`` of similarities (N, 4, 4): ``s R`` has columns of length ``s``."""
    return torch.linalg.norm(poses[:, :3, 0], dim=-1).log()


def _scale_prior_cost(graph: PoseGraph, poses: torch.Tensor) -> float:
    if graph.scale_information is None:
        return 0.0
    return float((graph.scale_information.to(poses) * _log_scales(poses) ** 2).sum())


def _gravity_directions(poses: torch.Tensor) -> torch.Tensor:
    """``R^T e_z`` (N, 3) of similarities (N, 4, 4) ``[s R | t]``: the world's up axis in each node's frame."""
    return poses[:, 2, :3] / torch.linalg.norm(poses[:, :3, 0], dim=-1, keepdim=True)


def _gravity_prior_cost(graph: PoseGraph, poses: torch.Tensor, reference: torch.Tensor) -> float:
    if graph.gravity_information is None:
        return 0.0
    r = _gravity_directions(poses) - reference
    return float((graph.gravity_information.to(poses) * (r * r).sum(-1)).sum())


def _robust_weights(graph: PoseGraph, r: torch.Tensor, huber_delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-edge IRLS weights and robust costs: Huber on the whitened norm ``m = sqrt(r^T L r)``."""
    m2 = torch.einsum("ea,eab,eb->e", r, graph.information, r)
    weights = torch.ones_like(m2)
    costs = m2.clone()
    if huber_delta > 0:
        m = m2.clamp_min(1e-300).sqrt()
        outer = graph.robust & (m > huber_delta)
        weights = torch.where(outer, huber_delta / m, weights)
        costs = torch.where(outer, 2 * huber_delta * m - huber_delta**2, costs)
    return weights, costs


def optimize_pose_graph(graph: PoseGraph, config: PoseGraphConfig | None = None) -> PoseGraphResult:
    """Minimise the pose-graph cost by Levenberg-Marquardt; returns new poses (input is not modified)."""
    config = config or PoseGraphConfig()
    poses = graph.poses.to(torch.float64).clone()
    n = poses.shape[0]
    free = torch.ones(n, dtype=torch.bool)
    free[graph.fixed] = False
    # Column offset of each free node in the reduced system (-1 for fixed nodes).
    offset = torch.full((n,), -1, dtype=torch.int64)
    offset[free] = torch.arange(int(free.sum())) * 7
    dim = int(free.sum()) * 7
    damping = config.initial_damping

    reference = _gravity_directions(poses)

    def prior_cost(p: torch.Tensor) -> float:
        return _scale_prior_cost(graph, p) + _gravity_prior_cost(graph, p, reference)

    r = _residuals(graph, poses)
    w, c = _robust_weights(graph, r, config.huber_delta)
    cost = float(c.sum()) + prior_cost(poses)
    prior_rows = (offset + 6)[free] if graph.scale_information is not None else None
    e_z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    costs = [cost]
    it = 0
    for it in range(1, config.max_iterations + 1):
        jl_inv = sim3_left_jacobian_inv(r)
        adj = sim3_adjoint(sim3_inverse(poses[graph.edges_i] @ graph.measurements))
        jj = jl_inv @ adj  # (E, 7, 7), d r / d d_j
        info = w[:, None, None] * graph.information
        b = torch.zeros(dim, dtype=torch.float64)
        blocks = {"i": -jj, "j": jj}
        idx = {"i": graph.edges_i, "j": graph.edges_j}
        triplets = []
        for a in ("i", "j"):
            ja = blocks[a]
            ga = (ja.transpose(-1, -2) @ info @ r[..., None])[..., 0]
            _scatter_vector(b, offset[idx[a]], ga)
            for bb in ("i", "j"):
                hab = ja.transpose(-1, -2) @ info @ blocks[bb]
                triplets.append(_block_triplets(offset[idx[a]], offset[idx[bb]], hab))
        if dim == 0:
            break
        if prior_rows is not None:
            lam = graph.scale_information.to(poses)[free]
            b.index_add_(0, prior_rows, lam * _log_scales(poses[free]))
            triplets.append((prior_rows.numpy(), prior_rows.numpy(), lam.numpy()))
        if graph.gravity_information is not None:   # rows phi = 3..5 of each free node
            mu = graph.gravity_information.to(poses)[free]
            R = poses[free, :3, :3] / torch.linalg.norm(poses[free, :3, 0], dim=-1)[:, None, None]
            J = R.transpose(-1, -2) @ hat(e_z)
            rg = _gravity_directions(poses[free]) - reference[free]
            _scatter_vector(b, offset[free] + 3, mu[:, None] * (J.transpose(-1, -2) @ rg[..., None])[..., 0])
            rows = offset[free] + 3
            triplets.append(_block_triplets(rows, rows, mu[:, None, None] * (J.transpose(-1, -2) @ J)))
        h = scipy.sparse.coo_matrix(
            (np.concatenate([t[2] for t in triplets]),
             (np.concatenate([t[0] for t in triplets]), np.concatenate([t[1] for t in triplets]))),
            shape=(dim, dim)).tocsc()  # duplicate entries are summed
        h_diag = np.maximum(h.diagonal(), 1e-12)
        new_cost = float("inf")
        while damping <= 1e12:
            step = _solve_spd((h + scipy.sparse.diags(damping * h_diag)).tocsc(), b.numpy())
            if step is not None:   # None: numerically singular, damp more
                trial = poses.clone()
                trial[free] = sim3_exp(step.view(-1, 7)) @ poses[free]
                r_trial = _residuals(graph, trial)
                w_trial, c_trial = _robust_weights(graph, r_trial, config.huber_delta)
                new_cost = float(c_trial.sum()) + prior_cost(trial)
                if new_cost < cost:
                    poses, r, w = trial, r_trial, w_trial
                    damping = max(damping / 10.0, 1e-12)
                    break
            damping *= 10.0
        decrease = (cost - new_cost) / max(cost, 1e-300) if new_cost < cost else 0.0
        cost = min(cost, new_cost)
        costs.append(cost)
        if decrease < config.tolerance:
            break
    return PoseGraphResult(poses=poses, initial_cost=costs[0], final_cost=cost, iterations=it, costs=costs)


def _solve_spd(A: scipy.sparse.csc_matrix, b: np.ndarray) -> torch.Tensor | None:
    """``-A^-1 b`` for the damped normal matrix ``A`` (symmetric positive definite), or None where its
    factorisation breaks down. SuperLU in symmetric mode (a minimum-degree ordering of ``A^T + A``, diagonal
    pivots, which positive definiteness makes safe) fills in far less than its default for general matrices on a
    chain of keyframes with loops."""
    try:
        lu = scipy.sparse.linalg.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                      options={"SymmetricMode": True})
    except RuntimeError:   # "Factor is exactly singular"
        return None
    x = lu.solve(b)
    return -torch.from_numpy(x) if np.isfinite(x).all() else None


def _scatter_vector(b: torch.Tensor, rows: torch.Tensor, values: torch.Tensor) -> None:
    """``b[rows[e] : rows[e] + k] += values[e]`` (values (E, k)) for nodes that are free (rows >= 0)."""
    keep = rows >= 0
    index = (rows[keep, None] + torch.arange(values.shape[-1])).reshape(-1)
    b.index_add_(0, index, values[keep].reshape(-1))


def _block_triplets(rows: torch.Tensor, cols: torch.Tensor,
                    blocks: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sparse ``(row, col, value)`` entries of ``h[rows[e]:+k, cols[e]:+k] += blocks[e]`` (blocks (E, k, k)) for
    pairs whose two nodes are free (rows, cols >= 0)."""
    keep = (rows >= 0) & (cols >= 0)
    k = blocks.shape[-1]
    ar = torch.arange(k)
    r_idx = (rows[keep, None, None] + ar[None, :, None]).expand(-1, k, k)
    c_idx = (cols[keep, None, None] + ar[None, None, :]).expand(-1, k, k)
    return r_idx.reshape(-1).numpy(), c_idx.reshape(-1).numpy(), blocks[keep].reshape(-1).numpy()
