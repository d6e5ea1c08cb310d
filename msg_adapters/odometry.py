"""``nav_msgs/Odometry`` and ``nav_msgs/Path`` <-> poses and :class:`vigs_core.types.Trajectory`.

Odometry (REP-105): ``pose`` is ``T_frame_child`` in ``header.frame_id`` (e.g. ``odom`` or ``map``);
``twist`` is expressed in ``child_frame_id`` (the body), so a world-frame velocity ``v_w`` is sent as
``v_b = R_wb^T v_w``. Covariances are 6x6 row-major over (x, y, z, rot x, rot y, rot z).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from msg_adapters.common import (
    check_pose_matrix,
    field,
    finite_array,
    header_stamp_ns,
    make_header,
    matrix_to_quat_xyzw,
    ns_to_stamp,
    numeric,
    pose_to_matrix,
    read_vector3,
    vector3,
)
from msg_adapters.types import MessageTypes, RclpyTypes
from vigs_core.types import Trajectory
from vigs_core.geometry import matrix_to_quat


def pose_to_odometry(types: MessageTypes, t_ns: int, T, frame_id: str, child_frame_id: str,
                     velocity_world=None, angular_velocity_body=None, pose_covariance=None,
                     twist_covariance=None):
    """A ``nav_msgs/Odometry`` for pose ``T`` (4, 4) of ``child_frame_id`` in ``frame_id``, every input checked
    (a rigid transform, finite values, a stamp >= 0).

    Args:
        velocity_world: (3,) linear velocity in ``frame_id`` (m/s), rotated into the body for ``twist``.
        angular_velocity_body: (3,) angular velocity in the body (rad/s).
        pose_covariance, twist_covariance: (6, 6) covariances; default zero (unknown).
    """
    ns_to_stamp(types, t_ns)
    T = check_pose_matrix(T, "pose")
    check = lambda x, shape, what: None if x is None else finite_array(x, shape, what)[None]  # noqa: E731
    return odometry_messages(types, [t_ns], T[None], frame_id, child_frame_id,
                             check(velocity_world, (3,), "velocity"), check(angular_velocity_body, (3,), "angular"),
                             check(pose_covariance, (6, 6), "pose_covariance"),
                             check(twist_covariance, (6, 6), "twist_covariance"))[0]


def odometry_messages(types: MessageTypes, t_ns, T, frame_id: str, child_frame_id: str, velocity_world=None,
                      angular_velocity_body=None, pose_covariance=None, twist_covariance=None) -> list:
    """``nav_msgs/Odometry`` messages of rigid poses ``T`` (N, 4, 4) at stamps ``t_ns`` (N,) >= 0, unchecked:
    for poses of the caller's own making at IMU rate, where :func:`pose_to_odometry`'s checks and keyword
    construction cost more than the propagation. ``velocity_world`` / ``angular_velocity_body`` (N, 3) or (3,)
    (see :func:`pose_to_odometry`); covariances (N, 6, 6) or (6, 6)."""
    T = np.asarray(T, dtype=np.float64)
    n = len(T)
    R = T[:, :3, :3]
    q = matrix_to_quat(R).tolist()   # (N, 4) w, x, y, z
    pos = T[:, :3, 3].tolist()
    v_b = (np.zeros((n, 3)) if velocity_world is None else
           np.einsum("nji,nj->ni", R, np.broadcast_to(np.asarray(velocity_world, np.float64), (n, 3)))).tolist()
    w_b = np.broadcast_to(np.zeros(3) if angular_velocity_body is None else
                          np.asarray(angular_velocity_body, np.float64), (n, 3)).tolist()
    cov = [None if c is None else np.broadcast_to(np.asarray(c, np.float64).reshape(-1, 36), (n, 36))
           for c in (pose_covariance, twist_covariance)]
    out = []
    if isinstance(types, RclpyTypes):   # fill default messages in place, several times cheaper than keywords
        make = types.message_class("nav_msgs/msg/Odometry")
        for k in range(n):
            m = make()
            m.header.frame_id, m.child_frame_id = frame_id, child_frame_id
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(t_ns[k]), 1_000_000_000)
            pose, twist = m.pose.pose, m.twist.twist
            pose.position.x, pose.position.y, pose.position.z = pos[k]
            rot = pose.orientation
            rot.w, rot.x, rot.y, rot.z = q[k]
            twist.linear.x, twist.linear.y, twist.linear.z = v_b[k]
            twist.angular.x, twist.angular.y, twist.angular.z = w_b[k]
            if cov[0] is not None:
                m.pose.covariance = np.ascontiguousarray(cov[0][k])
            if cov[1] is not None:
                m.twist.covariance = np.ascontiguousarray(cov[1][k])
            out.append(m)
        return out
    new = types.new
    zero = np.zeros(36)
    for k in range(n):
        (x, y, z), (qw, qx, qy, qz) = pos[k], q[k]
        out.append(new(
            "nav_msgs/msg/Odometry",
            header=make_header(types, int(t_ns[k]), frame_id),
            child_frame_id=str(child_frame_id),
            pose=new("geometry_msgs/msg/PoseWithCovariance",
                     pose=new("geometry_msgs/msg/Pose", position=new("geometry_msgs/msg/Point", x=x, y=y, z=z),
                              orientation=new("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)),
                     covariance=zero if cov[0] is None else np.array(cov[0][k])),
            twist=new("geometry_msgs/msg/TwistWithCovariance",
                      twist=new("geometry_msgs/msg/Twist", linear=vector3(types, v_b[k]),
                                angular=vector3(types, w_b[k])),
                      covariance=zero if cov[1] is None else np.array(cov[1][k])),
        ))
    return out


def odometry_to_pose(msg) -> dict:
    """Fields of an Odometry message as numpy: ``t_ns``, ``frame_id``, ``child_frame_id``, ``T`` (4, 4),
    ``velocity_world`` (3,) (the body twist rotated into ``frame_id``), ``angular_velocity_body`` (3,),
    ``pose_covariance`` (6, 6), ``twist_covariance`` (6, 6)."""
    t_ns = header_stamp_ns(msg, "Odometry")
    pose_cov = field(msg, "pose", "Odometry")
    twist_cov = field(msg, "twist", "Odometry")
    T = pose_to_matrix(field(pose_cov, "pose", "Odometry.pose"), "Odometry.pose.pose")
    twist = field(twist_cov, "twist", "Odometry.twist")
    v_b = read_vector3(field(twist, "linear", "Odometry.twist"), "Odometry.twist.linear")
    w_b = read_vector3(field(twist, "angular", "Odometry.twist"), "Odometry.twist.angular")
    return {
        "t_ns": t_ns,
        "frame_id": str(msg.header.frame_id),
        "child_frame_id": str(field(msg, "child_frame_id", "Odometry")),
        "T": T,
        "velocity_world": T[:3, :3] @ v_b,
        "angular_velocity_body": w_b,
        "pose_covariance": finite_array(numeric(pose_cov.covariance, np.float64, "cov"), (6, 6), "pose covariance"),
        "twist_covariance": finite_array(numeric(twist_cov.covariance, np.float64, "cov"), (6, 6), "twist covariance"),
    }


def trajectory_to_path(types: MessageTypes, traj: Trajectory, frame_id: str, t_ns: int | None = None):
    """A ``nav_msgs/Path`` of a trajectory (:func:`poses_to_path`); header stamp = ``t_ns`` or the last pose's
    stamp (0 for an empty trajectory)."""
    stamp = t_ns if t_ns is not None else (int(traj.t_ns[-1]) if len(traj) else 0)
    return poses_to_path(types, traj.t_ns, traj.matrices(), frame_id, stamp)


def poses_to_path(types: MessageTypes, t_ns: np.ndarray, T: np.ndarray, frame_id: str, stamp_ns: int):
    """A ``nav_msgs/Path`` of rigid poses (N, 4, 4) at stamps (N,) ns in ``frame_id``, header stamp ``stamp_ns``
    (:func:`pose_stamped_messages`)."""
    return types.new("nav_msgs/msg/Path", header=make_header(types, int(stamp_ns), frame_id),
                     poses=pose_stamped_messages(types, t_ns, T, frame_id))


def pose_stamped_messages(types: MessageTypes, t_ns: np.ndarray, T: np.ndarray, frame_id: str) -> list:
    """``geometry_msgs/PoseStamped`` messages of rigid poses (N, 4, 4) at stamps (N,) ns in ``frame_id``: the
    quaternions of all poses in one batched conversion and no per-pose checks (:func:`pose_msg` per pose is too
    slow for a node that republishes a growing path; docs/benchmarks.md, live operation)."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    q = matrix_to_quat(T[:, :3, :3]).tolist()   # (N, 4) w, x, y, z
    rows = zip(np.asarray(t_ns).tolist(), T[:, :3, 3].tolist(), q)
    new = types.new
    if isinstance(types, RclpyTypes):   # rclpy: fill default messages in place, 6x cheaper than keyword construction
        make = types.message_class("geometry_msgs/msg/PoseStamped")
        poses = []
        for t, (x, y, z), (qw, qx, qy, qz) in rows:
            ps = make()
            ps.header.frame_id = frame_id
            ps.header.stamp.sec, ps.header.stamp.nanosec = divmod(int(t), 1_000_000_000)
            pos, rot = ps.pose.position, ps.pose.orientation
            pos.x, pos.y, pos.z = x, y, z
            rot.x, rot.y, rot.z, rot.w = qx, qy, qz, qw
            poses.append(ps)
        return poses
    return [new("geometry_msgs/msg/PoseStamped", header=make_header(types, int(t), frame_id),
                pose=new("geometry_msgs/msg/Pose", position=new("geometry_msgs/msg/Point", x=x, y=y, z=z),
                         orientation=new("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)))
            for t, (x, y, z), (qw, qx, qy, qz) in rows]


class KeyframePath:
    """A ``nav_msgs/Path`` of the newest ``max_poses`` keyframes, kept between publications: a keyframe's pose
    message is built when the keyframe is new or moved (:meth:`set`), not at every publication. A long run
    republishes thousands of keyframe poses every second, of which a frame moves only the window's few
    (docs/benchmarks.md, issue 22)."""

    def __init__(self, types: MessageTypes, frame_id: str, max_poses: int) -> None:
        if max_poses < 1:
            raise ValueError(f"KeyframePath needs max_poses >= 1, got {max_poses}")
        self.types, self.frame_id, self.max_poses = types, frame_id, int(max_poses)
        self._poses: dict[int, Any] = {}   # keyframe id -> PoseStamped, ascending ids

    def __len__(self) -> int:
        return len(self._poses)

    def set(self, ids: list[int], t_ns: np.ndarray, T: np.ndarray) -> None:
        """Keyframes ``ids`` (N,) are at poses ``T`` (N, 4, 4), stamps ``t_ns`` (N,) ns, now (new or moved). Ids older
        than every kept one once the path is full are left out: they fell off its start."""
        oldest = next(iter(self._poses)) if len(self._poses) >= self.max_poses else None
        rows = [n for n, k in enumerate(ids) if oldest is None or k >= oldest or k in self._poses]
        if not rows:
            return
        messages = pose_stamped_messages(self.types, np.asarray(t_ns)[rows], np.asarray(T)[rows], self.frame_id)
        inside = False   # an id added between kept ones
        for n, msg in zip(rows, messages):
            k = int(ids[n])
            inside |= k not in self._poses and bool(self._poses) and k < next(reversed(self._poses))
            self._poses[k] = msg
        if inside:   # keep the path in id order
            self._poses = dict(sorted(self._poses.items()))
        while len(self._poses) > self.max_poses:
            del self._poses[next(iter(self._poses))]

    def message(self, stamp_ns: int):
        """The path now, header stamp ``stamp_ns``."""
        return self.types.new("nav_msgs/msg/Path", header=make_header(self.types, int(stamp_ns), self.frame_id),
                              poses=list(self._poses.values()))


def path_to_trajectory(msg) -> Trajectory:
    """Trajectory of a Path (stamps from each PoseStamped's header)."""
    poses = field(msg, "poses", "Path")
    t = np.zeros(len(poses), np.int64)
    pos = np.zeros((len(poses), 3))
    quat = np.zeros((len(poses), 4))
    for i, ps in enumerate(poses):
        t[i] = header_stamp_ns(ps, f"Path.poses[{i}]")
        T = pose_to_matrix(field(ps, "pose", f"Path.poses[{i}]"), f"Path.poses[{i}].pose")
        pos[i] = T[:3, 3]
        x, y, z, w = matrix_to_quat_xyzw(T[:3, :3])
        quat[i] = (w, x, y, z)
    return Trajectory(t, pos, quat)
