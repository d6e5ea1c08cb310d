"""Shared pieces of the adapters: stamps, headers, poses and duck-typed field reading.

Conventions: stamps are integer nanoseconds (``builtin_interfaces/Time`` = ``sec * 1e9 + nanosec``);
poses are (4, 4) float64 homogeneous matrices ``T_parent_child``; ROS quaternions are ``(x, y, z, w)``,
vigs_core's are ``(w, x, y, z)``.
"""
from __future__ import annotations

import math

import numpy as np

from msg_adapters.types import MessageTypes


def field(msg, name: str, what: str):
    """``msg.name``, or a ValueError naming the message kind (``what``) and the missing field."""
    try:
        return getattr(msg, name)
    except AttributeError:
        raise ValueError(f"{what}: message of type {type(msg).__name__} has no field {name!r}") from None


def stamp_to_ns(stamp) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (``sec`` >= 0 and ``0 <= nanosec < 1e9``)."""
    sec = int(field(stamp, "sec", "Time"))
    nanosec = int(field(stamp, "nanosec", "Time"))
    if not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"Time.nanosec must be in [0, 1e9), got {nanosec}")
    return sec * 1_000_000_000 + nanosec


def ns_to_stamp(types: MessageTypes, t_ns: int):
    """A ``builtin_interfaces/Time`` for ``t_ns`` nanoseconds (>= 0)."""
    t_ns = int(t_ns)
    if t_ns < 0:
        raise ValueError(f"a ROS time stamp must be >= 0 ns, got {t_ns}")
    sec, nanosec = divmod(t_ns, 1_000_000_000)
    return types.new("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def make_header(types: MessageTypes, t_ns: int, frame_id: str):
    return types.new("std_msgs/msg/Header", stamp=ns_to_stamp(types, t_ns), frame_id=str(frame_id))


def header_stamp_ns(msg, what: str) -> int:
    return stamp_to_ns(field(field(msg, "header", what), "stamp", what))


def vector3(types: MessageTypes, v) -> object:
    v = finite_array(v, (3,), "Vector3")
    return types.new("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


def read_vector3(msg, what: str) -> np.ndarray:
    """(3,) float64 of a Vector3/Point; ValueError if a component is missing or not finite."""
    v = np.array([float(field(msg, k, what)) for k in "xyz"], dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{what}: non-finite vector {v.tolist()}")
    return v


def finite_array(values, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``values`` as a float64 array of ``shape``, checked finite."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != math.prod(shape):
        raise ValueError(f"{what}: expected {math.prod(shape)} values (shape {shape}), got {arr.size}")
    arr = arr.reshape(shape)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what}: non-finite values in {arr.tolist()}")
    return arr


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a Hamilton quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a (3, 3) rotation (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def read_quaternion(msg, what: str) -> np.ndarray:
    """(4,) ``(x, y, z, w)`` of a Quaternion; ValueError if not finite or far from unit norm."""
    q = np.array([float(field(msg, k, what)) for k in "xyzw"], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.all(np.isfinite(q)) or abs(norm - 1.0) > 1e-3:
        raise ValueError(f"{what}: expected a unit quaternion (x, y, z, w), got {q.tolist()} (norm {norm:.6g})")
    return q / norm


def check_pose_matrix(T, what: str) -> np.ndarray:
    """``T`` as a (4, 4) float64 rigid transform; ValueError if its rotation block is not a rotation."""
    T = finite_array(T, (4, 4), what)
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f"{what}: expected a rigid transform (rotation block orthonormal, last row 0 0 0 1)")
    return T


def quaternion_msg(types: MessageTypes, rot) -> object:
    """``geometry_msgs/Quaternion`` of a (3, 3) rotation matrix."""
    q = matrix_to_quat_xyzw(rot)
    return types.new("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])


def pose_msg(types: MessageTypes, T) -> object:
    """``geometry_msgs/Pose`` of a (4, 4) rigid transform."""
    T = check_pose_matrix(T, "pose")
    return types.new(
        "geometry_msgs/msg/Pose",
        position=types.new("geometry_msgs/msg/Point", x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=quaternion_msg(types, T[:3, :3]),
    )


def pose_to_matrix(msg, what: str = "Pose") -> np.ndarray:
    """(4, 4) float64 of a ``geometry_msgs/Pose``."""
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(read_quaternion(field(msg, "orientation", what), f"{what}.orientation"))
    T[:3, 3] = read_vector3(field(msg, "position", what), f"{what}.position")
    return T


def transform_msg(types: MessageTypes, T) -> object:
    """``geometry_msgs/Transform`` of a (4, 4) rigid transform."""
    T = check_pose_matrix(T, "transform")
    return types.new(
        "geometry_msgs/msg/Transform",
        translation=vector3(types, T[:3, 3]),
        rotation=quaternion_msg(types, T[:3, :3]),
    )


def transform_to_matrix(msg, what: str = "Transform") -> np.ndarray:
    """(4, 4) float64 of a ``geometry_msgs/Transform``."""
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(read_quaternion(field(msg, "rotation", what), f"{what}.rotation"))
    T[:3, 3] = read_vector3(field(msg, "translation", what), f"{what}.translation")
    return T


def numeric(values, dtype, what: str) -> np.ndarray:
    """A 1-D numpy view/copy of a sequence field (numpy array, ``array.array``, bytes or list)."""
    if isinstance(values, np.ndarray):
        return values.reshape(-1).astype(dtype, copy=False)
    if isinstance(values, (bytes, bytearray, memoryview)) and np.dtype(dtype) == np.uint8:
        return np.frombuffer(values, dtype=np.uint8)
    try:
        return np.asarray(values, dtype=dtype).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected a numeric sequence, got {type(values).__name__}: {exc}") from None
