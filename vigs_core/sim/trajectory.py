"""Continuous body motions for the simulator: poses and their derivatives at any time.

A motion gives, at stamps ``t_ns`` (int64 ns; converted to seconds after subtracting the motion's
start stamp, so float64 keeps sub-nanosecond resolution), the body pose ``(R_WB, p_WB)`` and the
kinematic quantities IMU synthesis needs: world acceleration ``p''`` (m/s^2), world velocity ``p'``
(m/s) and body angular rate ``omega_B = vee(R_WB^T R_WB')`` (rad/s).

* :class:`ProceduralMotion` -- sums of sinusoids in position and in Z-Y-X Euler angles, with exact
  analytic derivatives; the body stays near level and the camera looks around the room.
* :class:`SplineMotion` -- a twice-differentiable interpolation of a sampled :class:`Trajectory`
  (cubic spline in position; cubic rotation spline, Kim, Kim & Shin, "A general construction scheme
  for unit quaternion curves with simple high order derivatives", SIGGRAPH 1995, as in
  ``scipy.spatial.transform.RotationSpline``), for trajectories without a recorded IMU.
* :func:`sampled_poses` -- the ground-truth convention for image poses: SLERP/linear interpolation of
  the recorded samples (:func:`vigs_core.geometry.interpolate_poses`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from vigs_core.geometry import interpolate_poses, matrix_to_quat, quat_to_matrix
from vigs_core.types import Trajectory


@dataclass
class MotionState:
    """Kinematics at N times.

    Attributes:
        rotation: (N, 3, 3) ``R_WB``.
        position: (N, 3) ``p_WB`` (m).
        velocity: (N, 3) world velocity (m/s).
        acceleration: (N, 3) world acceleration ``p''`` (m/s^2), gravity not included.
        omega_body: (N, 3) body angular rate (rad/s).
    """

    rotation: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    omega_body: np.ndarray


@dataclass(frozen=True)
class ProceduralConfig:
    """Shape of a :class:`ProceduralMotion`.

    Args:
        duration_s: length of the motion (s).
        amplitude_xy: horizontal amplitude of each position sinusoid (m).
        amplitude_z: vertical amplitude of each position sinusoid (m).
        yaw_amplitude: amplitude of each yaw sinusoid (rad).
        tilt_amplitude: amplitude of the roll and pitch sinusoids (rad).
        min_period_s: shortest period of any sinusoid (s); longer periods mean gentler motion.
        max_period_s: longest period (s).
        height: mean height of the body above the world origin (m).
    """

    duration_s: float = 30.0
    amplitude_xy: float = 0.8
    amplitude_z: float = 0.15
    yaw_amplitude: float = 0.8
    tilt_amplitude: float = 0.12
    min_period_s: float = 4.0
    max_period_s: float = 14.0
    height: float = 1.2


# R_0 maps a camera looking along world +x (camera z -> world x, camera x -> world -y, camera y -> world -z)
_R_WC_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class ProceduralMotion:
    """Smooth random motion: ``p(t) = c + sum_k A_k sin(w_k t + phi_k)`` per axis and
    ``R_WB(t) = Rz(psi) Ry(theta) Rx(phi) R_0``, with each Euler angle a sum of sinusoids.

    ``R_0 = R_WC,level R_BC^T`` puts the camera level and looking along world +x at zero angles. The body
    rate of ``E = Rz(psi) Ry(theta) Rx(phi)`` is ``omega_E = (phi' - psi' s_theta,
    theta' c_phi + psi' c_theta s_phi, -theta' s_phi + psi' c_theta c_phi)`` and
    ``omega_B = R_0^T omega_E`` (the constant ``R_0`` does not add rate).

    Args:
        seed: draws amplitudes, periods and phases.
        R_BC: (3, 3) camera orientation in the body (from the camera-IMU extrinsic ``T_BS``).
        config: shape settings.
        start_ns: stamp (ns) of ``t = 0``.
    """

    n_terms = 3

    def __init__(
        self, seed: int, R_BC: np.ndarray, config: ProceduralConfig = ProceduralConfig(), start_ns: int = 10**9
    ) -> None:
        rng = np.random.default_rng([seed, 3])
        self.config = config
        self.start_ns = int(start_ns)
        self.end_ns = self.start_ns + int(round(config.duration_s * 1e9))
        self.R0 = _R_WC_LEVEL @ np.asarray(R_BC, dtype=np.float64).T
        k = self.n_terms

        def terms(amplitude: float, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            amp = amplitude * rng.uniform(0.5, 1.0, (count, k)) / np.sqrt(k)
            omega = 2 * np.pi / rng.uniform(config.min_period_s, config.max_period_s, (count, k))
            phase = rng.uniform(0, 2 * np.pi, (count, k))
            return amp, omega, phase

        a_xy, w_xy, f_xy = terms(config.amplitude_xy, 2)
        a_z, w_z, f_z = terms(config.amplitude_z, 1)
        self.pos_terms = (np.concatenate([a_xy, a_z]), np.concatenate([w_xy, w_z]), np.concatenate([f_xy, f_z]))
        # start the motion at the centre: subtract the value at t = 0
        a, w, f = self.pos_terms
        self.pos_offset = np.array([0.0, 0.0, config.height]) - (a * np.sin(f)).sum(axis=1)
        amps = np.array([[config.yaw_amplitude], [config.tilt_amplitude], [config.tilt_amplitude]])
        a_e, w_e, f_e = terms(1.0, 3)
        self.euler_terms = (a_e * amps, w_e, f_e)  # rows: yaw psi, pitch theta, roll phi

    @staticmethod
    def _series(terms: tuple[np.ndarray, np.ndarray, np.ndarray], t: np.ndarray) -> tuple[np.ndarray, ...]:
        """Values, first and second derivatives (each (N, rows)) of rows of sinusoid sums at t (N,)."""
        a, w, f = terms
        arg = t[:, None, None] * w[None] + f[None]  # (N, rows, k)
        value = (a * np.sin(arg)).sum(axis=2)
        first = (a * w * np.cos(arg)).sum(axis=2)
        second = -(a * w * w * np.sin(arg)).sum(axis=2)
        return value, first, second

    def evaluate(self, t_ns: np.ndarray) -> MotionState:
        """Kinematics at stamps ``t_ns`` (N,) (ns)."""
        t = (np.asarray(t_ns, dtype=np.int64).reshape(-1) - self.start_ns) * 1e-9
        p, v, acc = self._series(self.pos_terms, t)
        e, de, _ = self._series(self.euler_terms, t)
        psi, theta, phi = e[:, 0], e[:, 1], e[:, 2]
        dpsi, dtheta, dphi = de[:, 0], de[:, 1], de[:, 2]
        euler = Rotation.from_euler("ZYX", np.stack([psi, theta, phi], axis=1)).as_matrix()
        sp, cp = np.sin(phi), np.cos(phi)
        st, ct = np.sin(theta), np.cos(theta)
        omega_e = np.stack([dphi - dpsi * st, dtheta * cp + dpsi * ct * sp, -dtheta * sp + dpsi * ct * cp], axis=1)
        return MotionState(
            rotation=euler @ self.R0,
            position=p + self.pos_offset,
            velocity=v,
            acceleration=acc,
            omega_body=omega_e @ self.R0,  # R_0^T omega_E, row-wise
        )

    def poses(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(R_WB (N, 3, 3), p_WB (N, 3))`` at stamps ``t_ns`` (N,) (ns)."""
        state = self.evaluate(t_ns)
        return state.rotation, state.position


class SplineMotion:
    """Twice-differentiable interpolation of a sampled trajectory (for IMU synthesis).

    Args:
        trajectory: body poses; stamps strictly increasing, at least 4 samples.
    """

    def __init__(self, trajectory: Trajectory) -> None:
        if len(trajectory) < 4:
            raise ValueError(f"SplineMotion: needs at least 4 trajectory samples, got {len(trajectory)}")
        self.start_ns = int(trajectory.t_ns[0])
        self.end_ns = int(trajectory.t_ns[-1])
        t = (trajectory.t_ns - self.start_ns) * 1e-9
        if np.any(np.diff(t) <= 0):
            raise ValueError("SplineMotion: trajectory stamps must be strictly increasing")
        self.position = CubicSpline(t, trajectory.position, axis=0)
        q = trajectory.quat_wxyz
        self.rotation = RotationSpline(t, Rotation.from_quat(q[:, [1, 2, 3, 0]]))

    def evaluate(self, t_ns: np.ndarray) -> MotionState:
        """Kinematics at stamps ``t_ns`` (N,) (ns, same clock as the trajectory stamps)."""
        t = (np.asarray(t_ns, dtype=np.int64).reshape(-1) - self.start_ns) * 1e-9
        return MotionState(
            rotation=self.rotation(t).as_matrix(),
            position=self.position(t),
            velocity=self.position(t, 1),
            acceleration=self.position(t, 2),
            omega_body=self.rotation(t, 1),  # RotationSpline's rate is in the body frame
        )

    def poses(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(R_WB (N, 3, 3), p_WB (N, 3))`` at stamps ``t_ns`` (N,) (ns)."""
        state = self.evaluate(t_ns)
        return state.rotation, state.position


class SampledMotion:
    """Poses of a recorded trajectory at arbitrary times by SLERP / linear interpolation (the usual
    ground-truth convention for image poses).

    Args:
        trajectory: body poses with strictly increasing stamps.
    """

    def __init__(self, trajectory: Trajectory) -> None:
        self.trajectory = trajectory
        self.start_ns = int(trajectory.t_ns[0])
        self.end_ns = int(trajectory.t_ns[-1])
        self._t = torch.from_numpy(trajectory.t_ns - self.start_ns).to(torch.float64) * 1e-9
        self._R = quat_to_matrix(torch.from_numpy(trajectory.quat_wxyz))
        self._p = torch.from_numpy(trajectory.position)

    def poses(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(R_WB (N, 3, 3), p_WB (N, 3))`` at stamps ``t_ns`` (N,) inside the recorded span."""
        query = torch.from_numpy((np.asarray(t_ns, dtype=np.int64).reshape(-1) - self.start_ns) * 1e-9)
        rot, pos = interpolate_poses(self._t, self._R, self._p, query)
        return rot.numpy(), pos.numpy()


def trajectory_from_motion(motion: ProceduralMotion | SplineMotion, t_ns: np.ndarray) -> Trajectory:
    """Sample a differentiable motion at stamps ``t_ns`` (N,) into a :class:`Trajectory` with velocity."""
    state = motion.evaluate(t_ns)
    quat = matrix_to_quat(torch.from_numpy(state.rotation)).numpy()
    return Trajectory(t_ns, state.position, quat, velocity=state.velocity)
