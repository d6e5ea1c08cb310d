"""Hamilton unit quaternions stored as ``(w, x, y, z)`` (..., 4).

EuRoC CSV files use this order; TUM trajectory text uses ``(x, y, z, w)``. The product is
Hamilton's (``i j = k``), so ``quat_to_matrix(q1 * q2) = quat_to_matrix(q1) @ quat_to_matrix(q2)``.
"""
from __future__ import annotations

import numpy as np
import torch

from vigs_core.arrays import array_module, constant_like, take_along


def quat_xyzw_to_wxyz(q: torch.Tensor) -> torch.Tensor:
    """Reorder TUM ``(x, y, z, w)`` to internal ``(w, x, y, z)``."""
    return torch.cat((q[..., 3:], q[..., :3]), -1)


def quat_wxyz_to_xyzw(q: torch.Tensor) -> torch.Tensor:
    """Reorder internal ``(w, x, y, z)`` to TUM ``(x, y, z, w)``."""
    return torch.cat((q[..., 1:], q[..., :1]), -1)


def quat_multiply(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``q1 * q2`` of (..., 4) quaternions in ``(w, x, y, z)`` order."""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ),
        -1,
    )


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a quaternion (..., 4) ``(w, x, y, z)``; the input is normalised first."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
            torch.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
            torch.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )


def _shepperd_basis() -> tuple[np.ndarray, np.ndarray]:
    """``(L^T (9, 16), c (16,))`` with ``L vec(m) + c`` the 4x4 candidate table of :func:`matrix_to_quat`: row ``k``
    is ``4 q_k q`` (before dividing by ``4 q_k``), its diagonal ``4 q_k^2`` the pivots ``1 + tr m``,
    ``1 + m00 - m11 - m22``, ... and the off-diagonal entries the sums and differences of opposite entries."""
    e = np.eye(9)
    m = lambda i, j: e[3 * i + j]  # noqa: E731 -- coefficient row of m_ij
    s21, s02, s10 = m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1)
    a01, a02, a12 = m(0, 1) + m(1, 0), m(0, 2) + m(2, 0), m(1, 2) + m(2, 1)
    p = [m(0, 0) + m(1, 1) + m(2, 2), m(0, 0) - m(1, 1) - m(2, 2), -m(0, 0) + m(1, 1) - m(2, 2),
         -m(0, 0) - m(1, 1) + m(2, 2)]
    L = np.stack([p[0], s21, s02, s10, s21, p[1], a01, a02, s02, a01, p[2], a12, s10, a02, a12, p[3]])
    return np.ascontiguousarray(L.T), np.eye(4).reshape(16)


_SHEPPERD_LT, _SHEPPERD_C = _shepperd_basis()


def matrix_to_quat(rot: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of rotation matrices (..., 3, 3), with ``w >= 0`` (a torch tensor or a
    NumPy array, as given).

    Shepperd's method: of the four algebraically equal formulas (one per largest of
    ``w^2, x^2, y^2, z^2``), take the one with the largest pivot, which is never below 1/2 and so
    keeps full precision for every rotation. The candidate table is linear in the matrix entries
    (:func:`_shepperd_basis`), so it is one matrix product, not a few dozen small operations.
    """
    xp = array_module(rot)
    flat = rot.reshape(*rot.shape[:-2], 9)
    candidates = (flat @ constant_like(_SHEPPERD_LT, rot) + constant_like(_SHEPPERD_C, rot)).reshape(
        *rot.shape[:-2], 4, 4)
    pivots = xp.diagonal(candidates, 0, -2, -1)
    best = pivots.argmax(-1)[..., None]
    chosen = take_along(candidates, best[..., None], -2)[..., 0, :]
    pivot = take_along(pivots, best, -1)
    q = chosen / (2.0 * xp.sqrt(xp.where(pivot > 1e-12, pivot, 1e-12)))
    q = q / xp.linalg.norm(q, None, -1, True)
    return xp.where(q[..., :1] < 0, -q, q)
