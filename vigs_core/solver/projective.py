"""Inverse-depth reprojection between keyframes, with analytic Jacobians (DROID-SLAM Eq. 3, VIGS-SLAM 3.1).

A source pixel ``p = (u, v)`` of keyframe ``i`` with inverse depth (disparity) ``d`` is the homogeneous point
``q = (x, y, 1, d)``, ``x = (u - cx) / fx``, ``y = (v - cy) / fy`` (the 3D point ``(x, y, 1) / d`` scaled by ``d``).
With world->camera poses ``T_i, T_j`` and ``T_ji = T_j T_i^{-1} = [R | t]`` the point in camera ``j`` is, up to
the positive factor ``1/d``, ``P = R (x, y, 1) + t d``; its projection ``pi(P) = (fx X/Z + cx, fy Y/Z + cy)``.
Writing it this way keeps points at infinity (``d = 0``) finite.

Left perturbations ``T' = Exp(xi) T`` with ``xi = (rho, phi)`` give (the homogeneous action of ``Exp(xi)`` on
``(P, d)`` is ``P + phi x P + rho d``):

* ``dP/dxi_j = [d I, -[P]x]``                       (3, 6)
* ``dP/dxi_i = -[d I, -[P]x] Ad(T_ji)``             (3, 6), since ``T_j (Exp(xi_i) T_i)^{-1} = Exp(-Ad(T_ji) xi_i) T_ji``
* ``dP/dd    = t``                                  (3,)

and ``d pi / dP = [[fx/Z, 0, -fx X/Z^2], [0, fy/Z, -fy Y/Z^2]]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from vigs_core.geometry import se3_adjoint, se3_inverse


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels of the image the coordinates refer to (undistorted images)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by ``factor`` (pixel centres at integer coordinates)."""
        return Intrinsics(self.fx * factor, self.fy * factor,
                          (self.cx + 0.5) * factor - 0.5, (self.cy + 0.5) * factor - 0.5)


@dataclass
class Reprojection:
    """Projections of source pixels into a target camera and (optionally) their Jacobians.

    Shapes for a batch of ``E`` edges with ``P`` pixels each: ``uv (E, P, 2)``, ``valid (E, P)`` (point in
    front of the target camera), ``J_i, J_j (E, P, 2, 6)`` w.r.t. the source / target pose, ``J_d (E, P, 2)``
    w.r.t. the source disparity, and ``Ad (E, 6, 6)`` the adjoint of ``T_ji`` (``J_i = -J_j Ad``).
    """

    uv: torch.Tensor
    valid: torch.Tensor
    J_i: torch.Tensor | None = None
    J_j: torch.Tensor | None = None
    J_d: torch.Tensor | None = None
    Ad: torch.Tensor | None = None


# A projection is valid when the point's depth in camera j is at least this fraction of its depth in camera i
# (``Z = d * z_j`` and the source ray has z = 1, so ``Z = z_j / z_i``).
MIN_DEPTH_RATIO = 0.05


def pixel_rays(coords: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
    """Normalised rays ``(x, y, 1)`` (P, 3) of pixel coordinates (P, 2)."""
    x = (coords[..., 0] - intr.cx) / intr.fx
    y = (coords[..., 1] - intr.cy) / intr.fy
    return torch.stack((x, y, torch.ones_like(x)), -1)


def target_jacobian_entries(xn, yn, d_over_z, intr: Intrinsics) -> tuple:
    """The 12 entries, row-major (rows u, v; columns rho, phi), of ``d pi/dxi_j = d pi/dP [d I, -[P]x]`` (module
    docstring) in closed form, from the normalised projection ``xn = X/Z``, ``yn = Y/Z`` and ``d / Z``.
    Elementwise, so it serves torch tensors (:func:`reproject`) and NumPy arrays
    (:func:`vigs_core.solver.pose_alignment.align_pose`) alike; the caller stacks them."""
    fx, fy = intr.fx, intr.fy
    fdz, gdz = fx * d_over_z, fy * d_over_z
    xy = xn * yn
    zero = 0.0 * xn
    return (fdz, zero, -fdz * xn, -fx * xy, fx * (1 + xn * xn), -fx * yn,
            zero, gdz, -gdz * yn, -fy * (1 + yn * yn), fy * xy, fy * xn)


def reproject(T_i: torch.Tensor, T_j: torch.Tensor, disp: torch.Tensor, coords: torch.Tensor,
              intr: Intrinsics, jacobians: bool = False, source_jacobian: bool = True) -> Reprojection:
    """Project source pixels of keyframes ``i`` into cameras ``j`` (see the module docstring).

    Args:
        T_i, T_j: world->camera poses of source and target, (E, 4, 4).
        disp: inverse depth of the source pixels, (E, P), 1/m in the map's scale.
        coords: source pixel coordinates, (P, 2) shared by all edges, or (E, P, 2).
        intr: pinhole intrinsics of those coordinates.
        jacobians: also return ``J_j, J_d``, ``Ad`` and (with ``source_jacobian``) ``J_i``.
        source_jacobian: compute ``J_i = -J_j Ad`` per pixel; callers that only need products with it
            (normal equations, pose-only alignment) pass False and use ``Ad``.
    """
    T_ji = T_j @ se3_inverse(T_i)                                 # (E, 4, 4)
    R, t = T_ji[:, :3, :3], T_ji[:, :3, 3]
    if coords.dim() == 2:   # shared rays: one (P, 3) x (3, 3E) product instead of E tiny ones
        E_ = T_ji.shape[0]
        rot = (pixel_rays(coords, intr) @ R.transpose(1, 2).permute(1, 0, 2).reshape(3, 3 * E_))
        rot = rot.view(-1, E_, 3).transpose(0, 1)                 # (E, P, 3) = R (x, y, 1) per edge
    else:
        rot = pixel_rays(coords, intr) @ R.transpose(1, 2)
    P = rot + t[:, None, :] * disp[..., None]                     # (E, P, 3)
    X, Y, Z = P.unbind(-1)
    valid = Z > MIN_DEPTH_RATIO
    Zs = torch.where(valid, Z, torch.ones_like(Z))
    inv_z = 1.0 / Zs
    xn, yn = X * inv_z, Y * inv_z                                  # x' = X/Z, y' = Y/Z
    fx, fy = intr.fx, intr.fy
    uv = torch.stack((fx * xn + intr.cx, fy * yn + intr.cy), -1)
    if not jacobians:
        return Reprojection(uv, valid)
    J_j = torch.stack(target_jacobian_entries(xn, yn, disp * inv_z, intr), -1).view(*xn.shape, 2, 6)
    E, P_ = disp.shape
    Ad = se3_adjoint(T_ji)
    J_i = -(J_j.reshape(E, 2 * P_, 6) @ Ad).reshape(E, P_, 2, 6) if source_jacobian else None
    J_d = torch.stack((fx * inv_z * (t[:, None, 0] - xn * t[:, None, 2]),
                       fy * inv_z * (t[:, None, 1] - yn * t[:, None, 2])), -1)
    return Reprojection(uv, valid, J_i, J_j, J_d, Ad)
