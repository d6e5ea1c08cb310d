"""Is the published odometry's covariance honest? Its error since the first metric frame, and the NEES.

The camera-rate odometry's pose drifts from where metric tracking started (REP-105 ``odom``, a frame the
estimate itself defines), so its error is measured the way a consumer sees it: the ground truth is moved rigidly
onto the estimate's pose at the first metric frame, and each later metric frame's position error (m) and rotation
error ``Log(R_est R_gt^T)`` (rad; about x and y the tilt, about z the yaw in a gravity-aligned frame) are taken
against it, in the estimate's frame. The normalised estimation error squared, ``e^T S^-1 e`` per frame, should
average the degrees of freedom when the covariance ``S`` is consistent (Bar-Shalom, "Estimation with Applications
to Tracking", 5.4).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vigs_core.eval.association import associate
from vigs_core.types import Trajectory


@dataclass
class DriftErrors:
    """Errors of the metric frames of an odometry against the ground truth anchored at its first metric frame.

    Attributes:
        t_ns: (K,) stamps of the metric frames paired with the ground truth.
        position: (K, 3) estimated positions (m).
        position_error: (K, 3) estimate minus anchored ground truth, world axes (m).
        rotation_error: (K, 3) ``Log(R_est R_gt^T)``, world axes (rad).
    """

    t_ns: np.ndarray
    position: np.ndarray
    position_error: np.ndarray
    rotation_error: np.ndarray


def drift_errors(gt: Trajectory, est: Trajectory, metric: np.ndarray, max_diff_s: float = 0.02) -> DriftErrors:
    """Errors of ``est``'s frames where ``metric`` (N,) bool is set, against ``gt`` anchored rigidly at the first
    of them (module docstring); pairs by stamp within ``max_diff_s``."""
    keep = np.flatnonzero(np.asarray(metric, dtype=bool))
    i_gt, i_k = associate(gt.t_ns, est.t_ns[keep], int(max_diff_s * 1e9))
    if len(i_k) == 0:
        raise ValueError("drift_errors: no metric frame of the estimate has a ground-truth pose")
    order = np.argsort(est.t_ns[keep][i_k], kind="stable")
    i_gt, i_est = i_gt[order], keep[i_k[order]]
    R_est = Rotation.from_matrix(est.matrices()[i_est, :3, :3])
    R_gt = Rotation.from_matrix(gt.matrices()[i_gt, :3, :3])
    A = R_est[0] * R_gt[0].inv()   # the rotation taking the ground truth's attitude at the anchor onto the estimate's
    p_gt = A.apply(gt.position[i_gt] - gt.position[i_gt[0]]) + est.position[i_est[0]]
    return DriftErrors(t_ns=est.t_ns[i_est], position=est.position[i_est],
                       position_error=est.position[i_est] - p_gt,
                       rotation_error=(R_est * (A * R_gt).inv()).as_rotvec())


def nees(errors: DriftErrors, covariances: np.ndarray) -> np.ndarray:
    """(K,) NEES per frame of ``errors`` under ``covariances`` (K, 6, 6) over (x, y, z, roll, pitch, yaw)."""
    e = np.concatenate((errors.position_error, errors.rotation_error), axis=1)
    return np.einsum("ki,ki->k", e, np.linalg.solve(covariances, e[:, :, None])[:, :, 0])
