"""Batched Lie-group geometry in PyTorch: SO(3), SE(3), Sim(3) and quaternions.

Conventions (used everywhere in the project):

* Rotations are 3x3 matrices ``(..., 3, 3)``; rigid and similarity transforms are homogeneous
  4x4 matrices ``(..., 4, 4)``. ``T_ab`` maps points from frame ``b`` into frame ``a``.
* Tangent vectors put translation first: SE(3) ``xi = (rho, phi)`` (6,), Sim(3)
  ``xi = (rho, phi, sigma)`` (7,) with scale ``s = exp(sigma)``.
* Perturbations are on the left unless a function says otherwise: ``T' = Exp(delta) T``.
* Quaternions are Hamilton, stored ``(w, x, y, z)`` internally (EuRoC order). TUM text files use
  ``(x, y, z, w)``; convert with :func:`quat_xyzw_to_wxyz` / :func:`quat_wxyz_to_xyzw`.

Float32 and float64 both work; use float64 for anything that accumulates (IMU, solver).
"""
from vigs_core.geometry.so3 import (
    hat,
    vee,
    nearest_rotation,
    relative_rotation_cosines,
    so3_exp,
    so3_log,
    so3_left_jacobian,
    so3_right_jacobian,
    so3_left_jacobian_inv,
    so3_right_jacobian_inv,
)
from vigs_core.geometry.quaternion import (
    quat_to_matrix,
    matrix_to_quat,
    quat_multiply,
    quat_xyzw_to_wxyz,
    quat_wxyz_to_xyzw,
)
from vigs_core.geometry.se3 import (
    se3_from_rt,
    se3_rotation,
    se3_translation,
    se3_exp,
    se3_log,
    se3_inverse,
    se3_compose,
    se3_act,
    se3_adjoint,
    se3_hat,
    se3_left_jacobian,
    se3_right_jacobian,
    se3_left_jacobian_inv,
    se3_right_jacobian_inv,
)
from vigs_core.geometry.sim3 import (
    sim3_from_srt,
    sim3_scale,
    sim3_exp,
    sim3_log,
    sim3_inverse,
    sim3_compose,
    sim3_act,
    sim3_adjoint,
    sim3_hat,
    sim3_left_jacobian,
    sim3_right_jacobian,
    sim3_left_jacobian_inv,
    sim3_right_jacobian_inv,
)
from vigs_core.geometry.interpolation import interpolate_poses

__all__ = [name for name in dir() if not name.startswith("_")]
