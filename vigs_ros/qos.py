"""QoS profiles of the VIGS graph (one place, so every publisher/subscriber pair is compatible).

* ``sensor_qos``: best-effort, keep-last, volatile (rclpy's ``qos_profile_sensor_data``) for camera and IMU
  inputs: drivers publish best-effort or reliable, and a best-effort subscriber accepts both.
* ``reliable_qos``: reliable, keep-last, volatile: odometry, path, keyframes, deltas between our nodes.
* ``latched_qos``: reliable, keep-last(1), transient-local: the last value reaches late joiners
  (camera info, latest state, ``/tf_static``, diagnostics).
* ``replay_qos``: reliable keep-last(100) for what bag replay publishes (recorded topics and ``/clock``;
  a reliable publisher matches best-effort subscribers too, e.g. rclpy's own ``/clock`` subscription).
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def sensor_qos(depth: int = 50) -> QoSProfile:
    """Best-effort keep-last(``depth``) volatile, for sensor inputs (depth covers bursts of 200 Hz IMU)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def reliable_qos(depth: int = 10) -> QoSProfile:
    """Reliable keep-last(``depth``) volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable keep-last(``depth``) transient-local: late joiners receive the last ``depth`` messages."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def replay_qos(depth: int = 100) -> QoSProfile:
    """Reliable keep-last(``depth``) volatile: what bag replay publishes recorded topics with (a reliable
    publisher matches best-effort and reliable subscribers alike)."""
    return reliable_qos(depth)
