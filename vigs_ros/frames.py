"""Frame maths for the TF tree of REP-105 (map -> odom -> base_link) and the camera-body extrinsic.

The estimator gives ``T_map_base`` (the body in the gravity-aligned world, which is the ``map`` frame).
REP-105 asks that ``odom -> base_link`` be continuous (no jumps) while ``map -> odom`` absorbs the
discrete corrections (loop closures, keyframe pose updates)::

    T_map_base = T_map_odom  T_odom_base

:class:`Rep105Frames` keeps ``T_odom_base`` continuous: after a correction (``mark_correction``) the next
estimate re-anchors ``T_map_odom = T_map_base_new T_odom_base_prev^-1`` (``T_odom_base`` continues from its
previous value, moved by the estimate's change since the previous estimate in the map frame). :meth:`reset_to_map`
is the one deliberate discontinuity: ``odom`` becomes the ``map`` frame again (the frontend's choice at the IMU
initialisation, so that ``odom`` is gravity-aligned, z up, as REP-103 and navigation stacks expect, rather
than the monocular start's camera frame).
"""
from __future__ import annotations

import numpy as np

from vigs_core.geometry import nearest_rotation


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform: ``[R^T, -R^T t]``."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def body_from_camera(T_w_c: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """``T_w_b = T_w_c T_b_c^-1``: body pose from a camera pose and the extrinsic ``T_b_c`` (camera in body)."""
    return T_w_c @ invert(T_b_c)


def camera_from_body(T_w_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """``T_w_c = T_w_b T_b_c``."""
    return T_w_b @ T_b_c


def matrix_from_param(values, name: str) -> np.ndarray:
    """A (4, 4) rigid transform from a 16-number row-major parameter; ValueError if not rigid."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != 16:
        raise ValueError(f"parameter {name}: expected 16 numbers (4x4 row-major), got {arr.size}")
    T = arr.reshape(4, 4)
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f"parameter {name}: not a rigid transform (rotation block orthonormal, last row 0 0 0 1)")
    T[:3, :3] = nearest_rotation(R)   # re-orthonormalise (calibration files print 8-10 digits)
    return T


class Rep105Frames:
    """Splits successive ``T_map_base`` estimates into ``T_map_odom`` and a continuous ``T_odom_base``."""

    def __init__(self) -> None:
        self.T_map_odom = np.eye(4)
        self._last_map_base: np.ndarray | None = None
        self._last_odom_base: np.ndarray | None = None
        self._corrected = False

    def reset_to_map(self) -> None:
        """From the next estimate on, ``odom`` is the ``map`` frame (``T_map_odom = I``): ``odom -> base_link`` jumps
        once, to the estimate itself."""
        self.T_map_odom = np.eye(4)
        self._corrected = False

    def mark_correction(self) -> None:
        """The next estimate follows a correction of the map frame: keep odom continuous across it."""
        self._corrected = True

    def update(self, T_map_base: np.ndarray, T_map_base_before_correction: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """``(T_map_odom, T_odom_base)`` for a new estimate.

        Args:
            T_map_base: (4, 4) the new estimate.
            T_map_base_before_correction: the estimate the estimator would have given for the same stamp
                without the correction; default: the previous estimate (odometry treats the body as having
                not moved across the correction).
        """
        if self._corrected and self._last_odom_base is not None:
            before = self._last_map_base if T_map_base_before_correction is None else T_map_base_before_correction
            # odom -> base continues by the uncorrected motion since the last estimate
            T_odom_base = self._last_odom_base @ invert(self._last_map_base) @ before
            self.T_map_odom = T_map_base @ invert(T_odom_base)
            # a product of every correction so far: keep it rigid, or its rounding error grows with each one
            self.T_map_odom[:3, :3] = nearest_rotation(self.T_map_odom[:3, :3])
            self._corrected = False
        T_odom_base = invert(self.T_map_odom) @ T_map_base
        self._last_map_base = T_map_base.copy()
        self._last_odom_base = T_odom_base
        return self.T_map_odom.copy(), T_odom_base
