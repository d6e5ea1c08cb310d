"""SO(3): exponential/logarithm maps and Jacobians, batched over leading dimensions.

Formulas follow Barfoot, "State Estimation for Robotics" (2017), Sec. 7.1, and Forster et al.,
"On-Manifold Preintegration" (T-RO 2017), Eq. (8) and (9):

* ``Exp(phi) = I + sin(t)/t [phi]x + (1 - cos(t))/t^2 [phi]x^2`` with ``t = |phi|`` (Rodrigues).
* ``J_r(phi) = I - (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2`` and ``J_l(phi) = J_r(-phi)``.
* ``J_r^{-1}(phi) = I + 1/2 [phi]x + (1/t^2 - (1 + cos t)/(2 t sin t)) [phi]x^2``.

Near ``t = 0`` every coefficient switches to its Taylor series, so values and autograd gradients
stay finite. The logarithm goes through the quaternion (Shepperd's method), which stays accurate
near ``t = pi`` where the trace formula loses all precision.
"""
from __future__ import annotations

import numpy as np
import torch

from vigs_core.arrays import array_module, constant_like

# Below this angle (rad) the trigonometric coefficients use their Taylor series.
_SMALL_ANGLE = 1e-4


# ``[v]x`` as a linear map of ``v``: column ``3 i + j`` holds ``-eps_ijk`` (Levi-Civita), so ``vec([v]x) = v E``.
_HAT_BASIS = np.array([[0, 0, 0, 0, 0, -1, 0, 1, 0],
                       [0, 0, 1, 0, 0, 0, -1, 0, 0],
                       [0, -1, 0, 1, 0, 0, 0, 0, 0]], dtype=np.float64)


def hat(v: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Skew-symmetric matrix ``[v]x`` of ``v`` (..., 3) -> (..., 3, 3), with ``[v]x w = v x w`` (a torch tensor
    or a NumPy array, as given).

    One product with the constant (3, 9) basis (entries 0 and +-1, so every entry is exactly ``+-v_k``):
    a single operation instead of a dozen, which matters for the many small batches of the inertial terms."""
    return (v @ constant_like(_HAT_BASIS, v)).reshape(*v.shape[:-1], 3, 3)


def nearest_rotation(m: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """The rotation nearest to ``m`` (..., 3, 3) in the Frobenius norm, ``U V^T`` of its SVD ``U S V^T``
    (orthogonal Procrustes; ``m`` near a rotation, det > 0). Products of rotations gather rounding error from
    one to the next: re-projecting keeps long-lived poses rigid. A torch tensor or a NumPy array, as given."""
    if isinstance(m, np.ndarray):
        u, _, vt = np.linalg.svd(m)
        return u @ vt
    u, _, vh = torch.linalg.svd(m)
    return u @ vh


def vee(m: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat`: (..., 3, 3) -> (..., 3); uses the antisymmetric part of ``m``."""
    return 0.5 * torch.stack(
        (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]), -1
    )


def _angle(phi: torch.Tensor | np.ndarray):
    """Return (theta, theta^2, small-mask) with theta safe to divide by (set to 1 where small)."""
    xp = array_module(phi)
    theta2 = (phi * phi).sum(-1)
    small = theta2 < _SMALL_ANGLE**2
    theta2_safe = xp.where(small, xp.ones_like(theta2), theta2)
    return xp.sqrt(theta2_safe), theta2, small


def rodrigues_coefficients(phi: torch.Tensor | np.ndarray):
    """Coefficients a = sin t / t, b = (1 - cos t)/t^2, c = (t - sin t)/t^3 (Taylor near 0), for a torch tensor
    or a NumPy array (..., 3) (the IMU preintegration runs in NumPy).

    Below ``_SMALL_ANGLE`` the series stop at ``t^2``: the next terms (``t^4 / 120`` and smaller) are below
    the float64 resolution of the leading 1, 1/2, 1/6 there."""
    xp = array_module(phi)
    theta, theta2, small = _angle(phi)
    sin, theta2_safe = xp.sin(theta), theta * theta
    a = xp.where(small, 1.0 - theta2 / 6.0, sin / theta)
    b = xp.where(small, 0.5 - theta2 / 24.0, (1.0 - xp.cos(theta)) / theta2_safe)
    c = xp.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - sin) / (theta2_safe * theta))
    return a, b, c


def exp_and_left_jacobian(phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``Exp(phi)`` and ``J_l(phi) = I + b [phi]x + c [phi]x^2`` (..., 3, 3) together, sharing the
    coefficients and ``[phi]x^2`` (what :func:`~vigs_core.geometry.se3.se3_exp` needs)."""
    a, b, c = (x[..., None, None] for x in rodrigues_coefficients(phi))
    k = hat(phi)
    k2 = k @ k
    eye = _eye_like(phi)
    return eye + a * k + b * k2, eye + b * k + c * k2


def _eye_like(phi: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    if isinstance(phi, np.ndarray):
        return np.broadcast_to(np.eye(3, dtype=phi.dtype), (*phi.shape[:-1], 3, 3))
    return torch.eye(3, dtype=phi.dtype, device=phi.device).expand(*phi.shape[:-1], 3, 3)


def so3_exp(phi: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Rotation matrix ``Exp(phi)`` for rotation vectors ``phi`` (..., 3) -> (..., 3, 3) (Rodrigues); like
    :func:`so3_log` and the right Jacobians, for a torch tensor or a NumPy array (the inertial factor runs in
    NumPy)."""
    a, b, _ = rodrigues_coefficients(phi)
    k = hat(phi)
    return _eye_like(phi) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Rotation vector ``Log(R)`` (..., 3, 3) -> (..., 3), angle in [0, pi].

    Computed from the unit quaternion ``q = (w, v)``: ``phi = 2 atan2(|v|, w) v / |v|``, with the
    sign of ``q`` chosen so ``w >= 0``; this is well conditioned for every angle including pi.
    """
    from vigs_core.geometry.quaternion import matrix_to_quat

    xp = array_module(rot)
    q = matrix_to_quat(rot)   # w >= 0
    w, v = q[..., 0], q[..., 1:]
    n2 = (v * v).sum(-1)
    small = n2 < 1e-12
    n = xp.sqrt(xp.where(small, xp.ones_like(n2), n2))
    # 2 atan2(n, w) / n ~ 2/w (1 - n^2/(3 w^2)) for small n.
    scale = xp.where(small, 2.0 / w - (2.0 / 3.0) * n2 / w**3, 2.0 * xp.atan2(n, w) / n)
    return scale[..., None] * v


def so3_right_jacobian(phi: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Right Jacobian ``J_r(phi)`` (..., 3, 3): ``Exp(phi + d) ~= Exp(phi) Exp(J_r(phi) d)``."""
    _, b, c = rodrigues_coefficients(phi)
    k = hat(phi)
    return _eye_like(phi) - b[..., None, None] * k + c[..., None, None] * (k @ k)


def so3_left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian ``J_l(phi) = J_r(-phi)``: ``Exp(phi + d) ~= Exp(J_l(phi) d) Exp(phi)``."""
    return so3_right_jacobian(-phi)


def so3_right_jacobian_inv(phi: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Inverse right Jacobian ``J_r^{-1}(phi)`` (..., 3, 3), closed form (Forster 2017, Eq. 9)."""
    xp = array_module(phi)
    theta, theta2, small = _angle(phi)
    # d = 1/t^2 - (1 + cos t) / (2 t sin t); Taylor: 1/12 + t^2/720 + t^4/30240.
    d = xp.where(
        small,
        1.0 / 12.0 + theta2 / 720.0 + theta2**2 / 30240.0,
        1.0 / theta**2 - (1.0 + xp.cos(theta)) / (2.0 * theta * xp.sin(theta)),
    )
    k = hat(phi)
    return _eye_like(phi) + 0.5 * k + d[..., None, None] * (k @ k)


def so3_left_jacobian_inv(phi: torch.Tensor) -> torch.Tensor:
    """Inverse left Jacobian ``J_l^{-1}(phi) = J_r^{-1}(-phi)``."""
    return so3_right_jacobian_inv(-phi)


def relative_rotation_cosines(R: torch.Tensor, R_batch: torch.Tensor) -> torch.Tensor:
    """``cos`` of the angle of ``R^T R_j`` for each rotation of ``R_batch`` (N, 3, 3), (N,):
    ``cos theta_j = (tr(R^T R_j) - 1) / 2`` with ``tr(A^T B) = sum_ab A_ab B_ab``; an angle test over many rotations
    without an SO(3) logarithm each."""
    return ((R_batch * R).sum(dim=(-2, -1)) - 1.0) / 2.0
