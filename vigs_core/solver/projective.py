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
    w.r.t. the source disparity.
    """

    uv: torch.Tensor
    valid: torch.Tensor
    J_i: torch.Tensor | None = None
    J_j: torch.Tensor | None = None
    J_d: torch.Tensor | None = None


# A projection is valid when the point's depth in camera j is at least this fraction of its depth in camera i
# (``Z = d * z_j`` and the source ray has z = 1, so ``Z = z_j / z_i``).
MIN_DEPTH_RATIO = 0.05


def pixel_rays(coords: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
    """Normalised rays ``(x, y, 1)`` (P, 3) of pixel coordinates (P, 2)."""
    x = (coords[..., 0] - intr.cx) / intr.fx
    y = (coords[..., 1] - intr.cy) / intr.fy
    return torch.stack((x, y, torch.ones_like(x)), -1)


def reproject(T_i: torch.Tensor, T_j: torch.Tensor, disp: torch.Tensor, coords: torch.Tensor,
              intr: Intrinsics, jacobians: bool = False) -> Reprojection:
    """Project source pixels of keyframes ``i`` into cameras ``j`` (see the module docstring).

    Args:
        T_i, T_j: world->camera poses of source and target, (E, 4, 4).
        disp: inverse depth of the source pixels, (E, P), 1/m in the map's scale.
        coords: source pixel coordinates, (P, 2) shared by all edges, or (E, P, 2).
        intr: pinhole intrinsics of those coordinates.
        jacobians: also return ``J_i, J_j, J_d``.
    """
    T_ji = T_j @ se3_inverse(T_i)                                 # (E, 4, 4)
    R, t = T_ji[:, :3, :3], T_ji[:, :3, 3]
    rays = pixel_rays(coords, intr).expand(disp.shape[0], -1, -1)   # (E, P, 3)
    P = rays @ R.transpose(1, 2) + t[:, None, :] * disp[..., None]  # (E, P, 3)
    X, Y, Z = P.unbind(-1)
    valid = Z > MIN_DEPTH_RATIO
    Zs = torch.where(valid, Z, torch.ones_like(Z))
    inv_z = 1.0 / Zs
    uv = torch.stack((intr.fx * X * inv_z + intr.cx, intr.fy * Y * inv_z + intr.cy), -1)
    if not jacobians:
        return Reprojection(uv, valid)
    # closed forms of d pi/dP . dP/dx with x' = X/Z, y' = Y/Z (see the module docstring)
    xn, yn = X * inv_z, Y * inv_z
    fx, fy = intr.fx, intr.fy
    dz = disp * inv_z
    J_j = torch.zeros(*X.shape, 2, 6, dtype=X.dtype, device=X.device)
    J_j[..., 0, 0] = fx * dz
    J_j[..., 0, 2] = -fx * dz * xn
    J_j[..., 0, 3] = -fx * xn * yn
    J_j[..., 0, 4] = fx * (1 + xn * xn)
    J_j[..., 0, 5] = -fx * yn
    J_j[..., 1, 1] = fy * dz
    J_j[..., 1, 2] = -fy * dz * yn
    J_j[..., 1, 3] = -fy * (1 + yn * yn)
    J_j[..., 1, 4] = fy * xn * yn
    J_j[..., 1, 5] = fy * xn
    E, P_ = disp.shape
    J_i = -(J_j.reshape(E, 2 * P_, 6) @ se3_adjoint(T_ji)).reshape(E, P_, 2, 6)
    J_d = torch.stack((fx * inv_z * (t[:, None, 0] - xn * t[:, None, 2]),
                       fy * inv_z * (t[:, None, 1] - yn * t[:, None, 2])), -1)
    return Reprojection(uv, valid, J_i, J_j, J_d)
