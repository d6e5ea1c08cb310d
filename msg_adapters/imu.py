"""``sensor_msgs/Imu`` <-> IMU samples (:class:`vigs_core.types.ImuSamples`).

An Imu message carries one sample: ``angular_velocity`` (rad/s) and ``linear_acceleration`` (m/s^2,
specific force, gravity included) in ``header.frame_id``; ``orientation`` is ignored (covariance[0] = -1
marks it unknown, as a raw IMU sends it).
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from msg_adapters.common import field, header_stamp_ns, make_header, read_vector3, vector3
from msg_adapters.types import MessageTypes
from vigs_core.types import ImuSamples


def imu_to_sample(msg) -> tuple[int, np.ndarray, np.ndarray]:
    """``(t_ns, gyro (3,) rad/s, acc (3,) m/s^2)`` of one Imu message.

    Raises:
        ValueError: missing fields or non-finite measurements.
    """
    t_ns = header_stamp_ns(msg, "Imu")
    gyro = read_vector3(field(msg, "angular_velocity", "Imu"), "Imu.angular_velocity")
    acc = read_vector3(field(msg, "linear_acceleration", "Imu"), "Imu.linear_acceleration")
    return t_ns, gyro, acc


def imu_messages_to_samples(msgs: Iterable) -> ImuSamples:
    """:class:`ImuSamples` of Imu messages, in the order given (not sorted: callers check order)."""
    rows = [imu_to_sample(m) for m in msgs]
    if not rows:
        return ImuSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    t, g, a = zip(*rows)
    return ImuSamples(np.array(t, np.int64), np.stack(g), np.stack(a))


def sample_to_imu(types: MessageTypes, t_ns: int, gyro, acc, frame_id: str = "imu",
                  gyro_variance: float = 0.0, acc_variance: float = 0.0):
    """A ``sensor_msgs/Imu`` for one sample; orientation marked unknown (covariance[0] = -1).

    Args:
        gyro_variance, acc_variance: per-axis variances ((rad/s)^2, (m/s^2)^2) for the diagonal
            covariances; 0 means unknown, as ROS does.
    """
    unknown = np.zeros(9)
    unknown[0] = -1.0
    return types.new(
        "sensor_msgs/msg/Imu",
        header=make_header(types, t_ns, frame_id),
        orientation=types.new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=unknown,
        angular_velocity=vector3(types, gyro),
        angular_velocity_covariance=np.eye(3).reshape(-1) * float(gyro_variance),
        linear_acceleration=vector3(types, acc),
        linear_acceleration_covariance=np.eye(3).reshape(-1) * float(acc_variance),
    )
