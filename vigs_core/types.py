"""Plain data types shared across vigs_core (numpy at the I/O boundary; torch inside algorithms).

Time stamps are integer nanoseconds (``np.int64``), as in EuRoC and ROS headers, so association by
stamp is exact; ``.t_s`` gives float seconds where arithmetic needs them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vigs_core.ranges import bounded


@dataclass
class ImuSamples:
    """A sequence of IMU samples in the IMU (body) frame.

    Attributes:
        t_ns: (N,) int64 sample stamps (ns), as recorded (not necessarily sorted: see ``io``).
        gyro: (N, 3) float64 angular velocity (rad/s).
        acc: (N, 3) float64 specific force (m/s^2), gravity included (reads +9.81 z when level at rest).
    """

    t_ns: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64)
        self.gyro = np.asarray(self.gyro, dtype=np.float64).reshape(-1, 3)
        self.acc = np.asarray(self.acc, dtype=np.float64).reshape(-1, 3)
        if not (len(self.t_ns) == len(self.gyro) == len(self.acc)):
            raise ValueError(
                f"ImuSamples: {len(self.t_ns)} stamps, {len(self.gyro)} gyro and {len(self.acc)} acc rows"
            )

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def t_s(self) -> np.ndarray:
        return self.t_ns.astype(np.float64) * 1e-9

    def slice(self, start_ns: int, end_ns: int) -> "ImuSamples":
        """Samples with ``start_ns <= t < end_ns``."""
        m = (self.t_ns >= start_ns) & (self.t_ns < end_ns)
        return ImuSamples(self.t_ns[m], self.gyro[m], self.acc[m])


@dataclass
class ImuNoise:
    """Continuous-time IMU noise model (Kalibr / EuRoC ``sensor.yaml`` conventions).

    Attributes:
        gyro_noise_density: gyroscope white noise, rad/s/sqrt(Hz).
        gyro_random_walk: gyroscope bias random walk, rad/s^2/sqrt(Hz).
        acc_noise_density: accelerometer white noise, m/s^2/sqrt(Hz).
        acc_random_walk: accelerometer bias random walk, m/s^3/sqrt(Hz).
        rate_hz: nominal sample rate (Hz).
        T_BS: (4, 4) pose of the IMU sensor in the body frame (identity for EuRoC).
    """

    gyro_noise_density: float = bounded(1.6968e-04, 0, lo_open=True)
    gyro_random_walk: float = bounded(1.9393e-05, 0, lo_open=True)
    acc_noise_density: float = bounded(2.0e-3, 0, lo_open=True)
    acc_random_walk: float = bounded(3.0e-3, 0, lo_open=True)
    rate_hz: float = bounded(200.0, 0, lo_open=True)
    T_BS: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass
class Trajectory:
    """A timed sequence of poses ``T_WX`` (frame X in the world W).

    Attributes:
        t_ns: (N,) int64 stamps (ns).
        position: (N, 3) float64 positions (m).
        quat_wxyz: (N, 4) float64 Hamilton unit quaternions, ``(w, x, y, z)``.
        velocity: optional (N, 3) world-frame velocities (m/s).
        bias_gyro: optional (N, 3) gyro biases (rad/s).
        bias_acc: optional (N, 3) accelerometer biases (m/s^2).
    """

    t_ns: np.ndarray
    position: np.ndarray
    quat_wxyz: np.ndarray
    velocity: np.ndarray | None = None
    bias_gyro: np.ndarray | None = None
    bias_acc: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64)
        self.position = np.asarray(self.position, dtype=np.float64).reshape(-1, 3)
        self.quat_wxyz = np.asarray(self.quat_wxyz, dtype=np.float64).reshape(-1, 4)
        if not (len(self.t_ns) == len(self.position) == len(self.quat_wxyz)):
            raise ValueError(
                f"Trajectory: {len(self.t_ns)} stamps, {len(self.position)} positions, "
                f"{len(self.quat_wxyz)} quaternions"
            )

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def t_s(self) -> np.ndarray:
        return self.t_ns.astype(np.float64) * 1e-9

    def matrices(self) -> np.ndarray:
        """(N, 4, 4) homogeneous poses ``T_WX`` (float64)."""
        import torch

        from vigs_core.geometry import quat_to_matrix, se3_from_rt

        rot = quat_to_matrix(torch.from_numpy(self.quat_wxyz))
        return se3_from_rt(rot, torch.from_numpy(self.position)).numpy()


@dataclass
class BadFrame:
    """In place of an image a source could not read or decode (a 0-byte or corrupt file, an undecodable message):
    ``reason`` says why; the run skips the frame with a warning."""

    reason: str
