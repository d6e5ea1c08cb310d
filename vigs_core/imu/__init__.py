"""IMU: preintegration, the inertial factor, propagation, initialisation and stream checks (issue 3).

| module | holds |
| --- | --- |
| ``samples`` | stream hygiene (gaps, out-of-order, duplicates; :class:`ImuDataWarning`) and the piecewise-constant measurements between two stamps (boundary samples interpolated) |
| ``preintegration`` | Forster on-manifold preintegration, vectorised over samples and intervals: deltas, 15x15 covariance, bias Jacobians, first-order bias correction |
| ``residual`` | the inertial factor of VIGS-SLAM Eq. (2)-(3), batched, with analytic Jacobians (camera poses, velocities, biases, gravity direction, log-scale) |
| ``propagation`` | state propagation (keyframe initialisation, IMU-rate odometry) |
| ``static_init`` | static-segment detection, static initialisation (gravity direction, gyro bias) |
| ``inertial_init`` | inertial-only initialisation (VIGS-SLAM 3.2): gravity, scale, velocities, biases, with a trust figure |
| ``init_scenario`` | initialisation scenarios built from real ground truth (benchmarks, tests) |
| ``analytic_motion`` | a smooth analytic motion with exact IMU measurements (tests, benchmarks) |
| ``check`` | the analysis behind ``vigs imu-check`` |

Conventions: float64 torch; stamps int64 ns; biases ``b = (b_g, b_a)``; the world is gravity-aligned
(z up) after initialisation, gravity ``(0, 0, -9.81)``; rotations ``R_wb`` body-to-world. Preintegration
errors and covariance are ordered ``(phi, v, p, b_g, b_a)`` with the rotation error on the right
(``dR_meas = dR Exp(d_phi)``) and velocity/position errors additive in the frame of the interval start.
"""
from vigs_core.imu.inertial_init import InertialInit, InertialInitConfig, inertial_only_init
from vigs_core.imu.preintegration import (
    Preintegrated,
    integrate_deltas,
    preintegrate,
    preintegrate_between,
    preintegrate_measurements,
    preintegrate_segments,
    stack_preintegrated,
)
from vigs_core.imu.propagation import ImuState, predict_state, propagate, propagate_path
from vigs_core.imu.residual import InertialResidual, gravity_rotation, inertial_residual
from vigs_core.imu.samples import ImuDataWarning, interval_measurements, sanitize_samples
from vigs_core.imu.static_init import StaticDetectorConfig, StaticInit, detect_static_segments, static_initialize

__all__ = [
    "ImuDataWarning",
    "ImuState",
    "InertialInit",
    "InertialInitConfig",
    "InertialResidual",
    "Preintegrated",
    "StaticDetectorConfig",
    "StaticInit",
    "detect_static_segments",
    "gravity_rotation",
    "inertial_only_init",
    "inertial_residual",
    "integrate_deltas",
    "interval_measurements",
    "predict_state",
    "preintegrate",
    "preintegrate_between",
    "preintegrate_measurements",
    "preintegrate_segments",
    "propagate",
    "propagate_path",
    "sanitize_samples",
    "stack_preintegrated",
    "static_initialize",
]
