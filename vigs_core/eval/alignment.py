"""Aligning an estimated trajectory to ground truth before measuring its error.

All alignments are similarity transforms ``x_gt ~= s R x_est + t`` fitted by least squares to
associated positions (float64 numpy):

* ``"sim3"``: rotation, translation and scale (7 DoF; monocular systems), Umeyama (1991).
* ``"se3"``: rotation and translation (6 DoF), Umeyama with ``s = 1``.
* ``"posyaw"``: rotation about the gravity axis z and translation (4 DoF; visual-inertial systems,
  whose roll, pitch and scale are observable), closed form below.
* ``"none"``: identity (the estimate is already in the ground-truth frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ALIGN_MODES = ("se3", "sim3", "posyaw", "none")
_MIN_POINTS = {"se3": 3, "sim3": 3, "posyaw": 2, "none": 1}


@dataclass(frozen=True)
class Alignment:
    """The similarity ``x_gt = scale * rotation @ x_est + translation`` that maps the estimate onto ground truth.

    Attributes:
        scale: s (> 0; 1 unless the mode is ``"sim3"``).
        rotation: (3, 3) R.
        translation: (3,) t (m).
        mode: the alignment mode that produced it.
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    mode: str

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous Sim(3) matrix ``[[s R, t], [0, 1]]``."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def apply_positions(self, positions: np.ndarray) -> np.ndarray:
        """Aligned positions (N, 3): ``s R p + t``."""
        return self.scale * positions @ self.rotation.T + self.translation

    def apply_poses(self, poses: np.ndarray) -> np.ndarray:
        """Aligned poses (N, 4, 4): rotation ``R R_i``, position ``s R p_i + t`` (the scale acts on positions only)."""
        out = np.array(poses, dtype=np.float64, copy=True)
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        out[:, :3, 3] = self.apply_positions(out[:, :3, 3])
        return out


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~= s R src + t`` (Umeyama, IEEE TPAMI 13(4), 1991, eqs. 34-43).

    With means ``mu_x, mu_y``, source variance ``sigma_x^2 = mean ||x - mu_x||^2`` and covariance
    ``Sigma_xy = mean (y - mu_y)(x - mu_x)^T = U D V^T``: ``R = U S V^T`` with ``S = diag(1, 1, -1)`` when
    ``det(U) det(V) < 0`` (else identity), ``s = tr(D S) / sigma_x^2`` (1 without scale),
    ``t = mu_y - s R mu_x``.

    Args:
        src: (N, 3) points to be mapped (the estimate).
        dst: (N, 3) target points (ground truth).
        with_scale: fit ``s`` (Sim(3)) or fix ``s = 1`` (SE(3)).

    Returns:
        ``(s, R (3, 3), t (3,))``.

    Raises:
        ValueError: fewer than 3 points, or points that lie on a line (rotation undetermined), or a
            source without spread when fitting scale.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama: expected two (N, 3) arrays of equal shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama: needs at least 3 point pairs, got {len(src)}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    cov = dst_c.T @ src_c / len(src)
    u, d, vt = np.linalg.svd(cov)
    if d[1] <= 1e-12 * max(d[0], 1e-300):
        raise ValueError(
            "umeyama: the point pairs are collinear (or all equal), so the rotation is undetermined; "
            "expected a trajectory that spans at least a plane"
        )
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = (u * sign) @ vt
    scale = 1.0
    if with_scale:
        var_src = float((src_c**2).sum(1).mean())
        if var_src <= 0.0:
            raise ValueError("umeyama: source points are all equal; scale is undetermined")
        scale = float((d * sign).sum() / var_src)
    translation = mu_dst - scale * rotation @ mu_src
    return scale, rotation, translation


def position_yaw_alignment(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation about z and translation, ``dst ~= Rz(theta) src + t`` (4 DoF).

    Closed form: with centred points ``x = src - mu_src``, ``y = dst - mu_dst``, the cost
    ``sum ||y - Rz x||^2`` depends on ``theta`` only through the xy-plane term
    ``-2 (A cos(theta) + B sin(theta))`` with ``A = sum(x_x y_x + x_y y_y)``, ``B = sum(x_x y_y - x_y y_x)``,
    so ``theta = atan2(B, A)`` and ``t = mu_dst - Rz mu_src`` (z is left untouched by Rz).
    Both point sets must be gravity-aligned (z up).

    Args:
        src: (N, 3) estimate positions; dst: (N, 3) ground-truth positions; N >= 2.

    Returns:
        ``(R (3, 3), t (3,))``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(
            f"position_yaw_alignment: expected two (N, 3) arrays of equal shape, got {src.shape} and {dst.shape}"
        )
    if len(src) < 2:
        raise ValueError(f"position_yaw_alignment: needs at least 2 point pairs, got {len(src)}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    x, y = src - mu_src, dst - mu_dst
    a = float((x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1]).sum())
    b = float((x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]).sum())
    if a == 0.0 and b == 0.0:
        raise ValueError("position_yaw_alignment: no horizontal motion, so the yaw is undetermined")
    theta = np.arctan2(b, a)
    c, s = np.cos(theta), np.sin(theta)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rotation, mu_dst - rotation @ mu_src


def align(gt: np.ndarray, est: np.ndarray, mode: str) -> Alignment:
    """Fit the alignment ``mode`` (one of :data:`ALIGN_MODES`) mapping associated ``est`` (N, 3) onto ``gt`` (N, 3)."""
    if mode not in ALIGN_MODES:
        raise ValueError(f"align: mode must be one of {', '.join(ALIGN_MODES)}, got '{mode}'")
    gt = np.asarray(gt, dtype=np.float64)
    est = np.asarray(est, dtype=np.float64)
    if len(est) < _MIN_POINTS[mode]:
        raise ValueError(f"align: mode '{mode}' needs at least {_MIN_POINTS[mode]} associated poses, got {len(est)}")
    if mode in ("se3", "sim3"):
        scale, rotation, translation = umeyama(est, gt, with_scale=mode == "sim3")
    elif mode == "posyaw":
        scale = 1.0
        rotation, translation = position_yaw_alignment(est, gt)
    else:
        scale, rotation, translation = 1.0, np.eye(3), np.zeros(3)
    return Alignment(scale, rotation, translation, mode)
