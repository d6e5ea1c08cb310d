"""Pose-only Gauss-Newton alignment of one frame against a keyframe with fixed depth (per-frame tracking).

Minimises ``sum_p conf_p rho(|u*_p - pi(T T_src^-1, d_p, p)|)`` over the frame's world->camera pose ``T`` with the
Huber ``rho`` by IRLS (weights ``min(1, delta / e)``, :func:`vigs_core.solver.robust.huber_weight`). The residual
model and its Jacobian are those of :mod:`vigs_core.solver.projective` (the target block ``J_j``, left
perturbation ``T' = Exp(xi) T``); each iteration solves ``(J^T W J + mu I) dx = J^T W r`` with a small damping
``mu = 1e-4 mean(diag) + 1e-9`` and updates ``T <- [Exp(phi) | rho] T``, which agrees with ``Exp(xi) T`` to first
order (same Gauss-Newton fixed point; Rodrigues for the rotation).

Six unknowns over the ~1.4k grid pixels of a keyframe: at that size torch's per-operation overhead is several
times the arithmetic, so the alignment runs in NumPy on the host whatever the inputs' device. On this project's
2-core CPU a 3-iteration alignment at 376x240 (1410 pixels) took 6.1 ms through torch and about 0.8 ms here.
The projection runs in the inputs' floating type (float32 in tracking); the pose and the 6x6 system in float64.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from vigs_core.arrays import host
from vigs_core.solver.projective import MIN_DEPTH_RATIO, Intrinsics, target_jacobian_entries


@dataclass
class PoseAlignment:
    """Outcome of :func:`align_pose`: the world->camera pose (4, 4), the RMS residual of the inlier
    correspondences (pixels) and the fraction of weighted correspondences within the Huber threshold."""

    pose: torch.Tensor
    rms: float
    inlier_ratio: float


def _project(T_rel: np.ndarray, rays: np.ndarray, disp: np.ndarray, intr: Intrinsics, jacobian: bool):
    """Pixels (P, 2) of the source points ``(ray, d)`` in the camera ``T_rel = T T_src^-1`` (4, 4), whether each
    lies in front (P,), and with ``jacobian`` the target Jacobian (P, 2, 6) (:mod:`vigs_core.solver.projective`)."""
    R, t = T_rel[:3, :3].astype(rays.dtype), T_rel[:3, 3].astype(rays.dtype)
    P = rays @ R.T + disp[:, None] * t
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    valid = Z > MIN_DEPTH_RATIO
    inv_z = 1.0 / np.where(valid, Z, 1.0)
    xn, yn = X * inv_z, Y * inv_z
    uv = np.stack((intr.fx * xn + intr.cx, intr.fy * yn + intr.cy), -1)
    if not jacobian:
        return uv, valid, None
    J = np.stack(target_jacobian_entries(xn, yn, disp * inv_z, intr), -1).reshape(-1, 2, 6)
    return uv, valid, J


def align_pose(T_src: torch.Tensor, disp: torch.Tensor, coords: torch.Tensor, intr: Intrinsics,
               target: torch.Tensor, weight: torch.Tensor, T_init: torch.Tensor, iterations: int = 6,
               huber_delta: float = 2.0) -> PoseAlignment:
    """Align a frame's pose to a keyframe's fixed depth (module docstring).

    Args:
        T_src: (4, 4) world->camera pose of the keyframe; disp (P,) its disparities at ``coords`` (P, 2).
        target: (P, 2) measured coordinates in the frame; weight (P,) confidences.
        T_init: (4, 4) initial world->camera pose of the frame.
        iterations: Gauss-Newton iterations (fewer when a step is below 1e-10 or the system is singular).
        huber_delta: Huber threshold on the residual norm, pixels.

    Returns:
        the pose with ``T_init``'s dtype and device, the inlier RMS and the inlier ratio.
    """
    dtype = np.float32 if disp.dtype == torch.float32 else np.float64
    d, uv_t, w0 = host(disp, dtype), host(target, dtype), host(weight, dtype)
    c = host(coords, np.float64)
    rays = np.stack(((c[:, 0] - intr.cx) / intr.fx, (c[:, 1] - intr.cy) / intr.fy, np.ones(len(c))), -1)
    rays = rays.astype(dtype)
    src = host(T_src, np.float64)
    src_inv = np.eye(4)
    src_inv[:3, :3] = src[:3, :3].T
    src_inv[:3, 3] = -src[:3, :3].T @ src[:3, 3]
    T = host(T_init, np.float64)
    for _ in range(iterations):
        uv, valid, J = _project(T @ src_inv, rays, d, intr, jacobian=True)
        r = uv_t - uv
        e = np.sqrt((r * r).sum(-1))
        w = w0 * np.minimum(1.0, huber_delta / np.maximum(e, 1e-12)) * valid
        Jf = J.reshape(-1, 6)
        WJ = (Jf * np.repeat(w, 2)[:, None]).astype(np.float64)
        H = WJ.T @ Jf
        g = WJ.T @ r.reshape(-1)
        H += np.eye(6) * (1e-4 * H.diagonal().mean() + 1e-9)
        try:
            L = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            break
        dx = np.linalg.solve(L.T, np.linalg.solve(L, g))
        if not np.isfinite(dx).all():
            break
        step = np.eye(4)
        step[:3, :3] = cv2.Rodrigues(dx[3:])[0]
        step[:3, 3] = dx[:3]
        T = step @ T
        if float(np.linalg.norm(dx)) < 1e-10:
            break
    uv, valid, _ = _project(T @ src_inv, rays, d, intr, jacobian=False)
    e = np.sqrt(((uv_t - uv) ** 2).sum(-1))
    inl = (e < huber_delta) & valid & (w0 > 0)
    wsum = float(w0.sum())
    rms = float(np.sqrt((e[inl].astype(np.float64) ** 2).mean())) if inl.any() else float("inf")
    ratio = float(w0[inl].sum()) / wsum if wsum > 0 else 0.0
    return PoseAlignment(torch.from_numpy(T).to(dtype=T_init.dtype, device=T_init.device), rms, ratio)
