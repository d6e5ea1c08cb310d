"""The covariance the camera-rate odometry is published with: a drift model calibrated on the hybrid sequences.

The odometry's pose is the causal VIO estimate in REP-105's continuous ``odom`` frame, never corrected by loop
closure, so its error against the true path grows with the distance travelled. The VI-BA's marginal covariance
describes the window relative to its own gauge, not that accumulated drift, so the published covariance is a
documented model instead, checked against the actual error by NEES
(:func:`vigs_core.eval.odometry_consistency.drift_errors`, ``benchmarks/odometry_covariance.py``)::

    sigma_position^2 = position_std^2 + (scale_std * r)^2 + (position_drift * d)^2     (each axis, m)
    sigma_yaw^2      = yaw_std^2 + (yaw_drift * d)^2                                    (rad)
    sigma_roll = sigma_pitch = tilt_std                                                 (gravity bounds them)

with ``r`` the distance from the first metric frame's position (an error of the metric scale moves every
position in proportion to it) and ``d`` the path length travelled while metric since then (the drift that
accumulates with motion, as VIO drift is usually reported). Roll and pitch are observable from gravity, so their
error against the attitude at the first metric frame stays bounded; yaw and position are not observable. The
defaults are calibrated on the causal odometry of the hybrid sequences (``vigs bench odometry_covariance``;
docs/benchmarks.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vigs_core.ranges import bounded
from vigs_core.vio.odometry import METRIC_STATUSES


@dataclass
class OdometryCovarianceConfig:
    """The drift model of the published odometry's covariance (module docstring) and its twist's constants.

    Args:
        position_std: position standard deviation per axis at the first metric frame, m.
        scale_std: relative error of the metric scale: the position standard deviation grows by this fraction
            of the distance from the first metric position.
        position_drift: growth of the position standard deviation per metre of path travelled while metric (a
            fraction of the path length).
        tilt_std: roll and pitch standard deviation, rad (held by gravity; does not grow).
        yaw_std: yaw standard deviation at the first metric frame, rad.
        yaw_drift: growth of the yaw standard deviation per metre travelled while metric, rad/m.
        velocity_std: linear velocity standard deviation of the twist, m/s per axis (the IMU-propagated frame
            velocity; a calibrated constant).
        angular_velocity_std: angular velocity standard deviation of the twist, rad/s per axis (one
            bias-corrected gyro sample, vibration included; a calibrated constant).
        unknown_std: standard deviation (m, rad, m/s, rad/s) reported while the estimator is not metric
            (initialising, lost, vision only) and for a twist it cannot give: do not fuse.
    """

    position_std: float = bounded(0.03, 0, lo_open=True)
    scale_std: float = bounded(0.025, 0)
    position_drift: float = bounded(0.001, 0)
    tilt_std: float = bounded(0.015, 0, lo_open=True)
    yaw_std: float = bounded(0.006, 0, lo_open=True)
    yaw_drift: float = bounded(0.0002, 0)
    velocity_std: float = bounded(0.03, 0, lo_open=True)
    angular_velocity_std: float = bounded(0.07, 0, lo_open=True)
    unknown_std: float = bounded(1000.0, 0, lo_open=True)


class OdometryCovariance:
    """Per-frame pose and twist covariances of the published odometry (:class:`OdometryCovarianceConfig`).

    Feed every published frame in order (:meth:`pose`); the distance counts the metric frames' motion only: a
    frame that is not metric reports the unknown covariance, and the first metric frame after it adds no jump.
    """

    def __init__(self, config: OdometryCovarianceConfig | None = None) -> None:
        self.config = config or OdometryCovarianceConfig()
        self.distance = 0.0
        self._origin: np.ndarray | None = None   # the first metric frame's position
        self._last: np.ndarray | None = None

    def restart(self) -> None:
        """The odometry frame was reset (e.g. to the gravity-aligned world at an IMU re-initialisation): the
        distances count again from the next metric frame."""
        self.distance, self._origin, self._last = 0.0, None, None

    def pose(self, position: np.ndarray, status: str) -> np.ndarray:
        """(6, 6) covariance of the pose (x, y, z, roll, pitch, yaw about the fixed frame's axes, REP-103) of a
        frame at ``position`` (3,) in the odometry frame, published with the estimator's ``status``."""
        c = self.config
        if status not in METRIC_STATUSES:
            self._last = None
            return _diagonal([c.unknown_std] * 6)
        position = np.asarray(position, dtype=np.float64)
        if self._origin is None:
            self._origin = position
        if self._last is not None:
            self.distance += float(np.linalg.norm(position - self._last))
        self._last = position
        r = float(np.linalg.norm(position - self._origin))
        sp = np.sqrt(c.position_std ** 2 + (c.scale_std * r) ** 2 + (c.position_drift * self.distance) ** 2)
        sy = np.hypot(c.yaw_std, c.yaw_drift * self.distance)
        return _diagonal([sp, sp, sp, c.tilt_std, c.tilt_std, sy])

    def twist(self, known: bool) -> np.ndarray:
        """(6, 6) covariance of the twist in the child frame: the calibrated constants when the frame has a metric
        twist (``known``), else the unknown one (the twist is then zero and must not be fused)."""
        c = self.config
        if known:
            return _diagonal([c.velocity_std] * 3 + [c.angular_velocity_std] * 3)
        return _diagonal([c.unknown_std] * 6)


def _diagonal(stds: list[float]) -> np.ndarray:
    """(6, 6) covariance with the squared standard deviations ``stds`` on its diagonal."""
    return np.diag(np.square(np.asarray(stds, dtype=np.float64)))
