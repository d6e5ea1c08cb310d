"""Imu, CameraInfo, Odometry, Path and TF adapters, for rclpy and rosbags classes, incl. malformed input."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from adapters_helpers import cdr_round_trip, types  # noqa: F401  (types is a fixture)

from msg_adapters.camera_info import camera_info_to_model, model_to_camera_info
from msg_adapters.common import matrix_to_quat_xyzw, quat_xyzw_to_matrix, stamp_to_ns
from msg_adapters.imu import imu_messages_to_samples, imu_to_sample, sample_to_imu
from msg_adapters.odometry import (KeyframePath, odometry_messages, odometry_to_pose, path_to_trajectory,
                                   pose_to_odometry, poses_to_path, trajectory_to_path)
from msg_adapters.tf import StampedTransform, tf_message, tf_message_to_transforms, transform_stamped
from vigs_core.camera import CameraModel
from vigs_core.geometry import so3_exp
from vigs_core.types import Trajectory


def random_pose(seed: int) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    T = np.eye(4)
    T[:3, :3] = so3_exp(torch.randn(3, generator=g, dtype=torch.float64)).numpy()
    T[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64).numpy()
    return T


def test_quaternion_conversions_match_core_geometry():
    from vigs_core.geometry import matrix_to_quat

    for seed in range(20):
        R = random_pose(seed)[:3, :3]
        q = matrix_to_quat_xyzw(R)
        np.testing.assert_allclose(quat_xyzw_to_matrix(q), R, atol=1e-12)
        w, x, y, z = matrix_to_quat(torch.from_numpy(R)).numpy()
        np.testing.assert_allclose(np.abs(np.dot(q, [x, y, z, w])), 1.0, atol=1e-9)


def test_imu_round_trip(types):
    msgs = [sample_to_imu(types, 1000 + 5_000_000 * i, [0.1 * i, 0.2, -0.3], [0.0, 0.1, 9.81], "imu4")
            for i in range(4)]
    msgs = [cdr_round_trip(types, m, "sensor_msgs/msg/Imu") for m in msgs]
    t, g, a = imu_to_sample(msgs[2])
    assert t == 10_001_000
    np.testing.assert_allclose(g, [0.2, 0.2, -0.3])
    np.testing.assert_allclose(a, [0.0, 0.1, 9.81])
    samples = imu_messages_to_samples(msgs)
    assert len(samples) == 4 and samples.gyro.shape == (4, 3)
    assert msgs[0].orientation_covariance[0] == -1.0
    assert len(imu_messages_to_samples([])) == 0


def test_malformed_imu_raises(types):
    msg = sample_to_imu(types, 0, [0, 0, 0], [0, 0, 9.8])
    msg.angular_velocity.x = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        imu_to_sample(msg)
    with pytest.raises(ValueError, match="no field 'angular_velocity'"):
        imu_to_sample(types.new("geometry_msgs/msg/Vector3Stamped", header=msg.header,
                                vector=msg.linear_acceleration))


CAMERAS = [
    CameraModel(752, 480, 458.654, 457.296, 367.215, 248.375, "radtan", (-0.28340811, 0.07395907, 0.00019359,
                                                                          1.76187114e-05)),
    CameraModel(512, 512, 190.97, 190.97, 254.93, 256.89, "equidistant", (0.0034, 0.0007, -0.0020, 0.0002)),
    CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5),
]


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.distortion)
def test_camera_info_round_trip(types, camera):
    msg = cdr_round_trip(types, model_to_camera_info(types, camera, 5, "cam0"), "sensor_msgs/msg/CameraInfo")
    assert msg.distortion_model == ("equidistant" if camera.distortion == "equidistant" else "plumb_bob")
    back = camera_info_to_model(msg)
    assert back.distortion == camera.distortion and back.width == camera.width
    np.testing.assert_allclose(back.coeffs + (0.0,) * (len(camera.coeffs) - len(back.coeffs)),
                               camera.coeffs + (0.0,) * (len(back.coeffs) - len(camera.coeffs)))
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [camera.fx, camera.fy, camera.cx, camera.cy])


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m, t: setattr(m, "distortion_model", "rational_polynomial"), "distortion_model"),
        (lambda m, t: setattr(m, "d", t.sequence([0.1, 0.2, 0.3], np.float64)), "3 coefficients"),
        (lambda m, t: setattr(m, "k", np.zeros(9)), "focal lengths"),
        (lambda m, t: setattr(m, "width", 0), "image size"),
        (lambda m, t: setattr(m, "binning_x", 2), "binning"),
    ],
)
def test_malformed_camera_info_raises(types, mutate, message):
    msg = model_to_camera_info(types, CAMERAS[0], 0, "cam")
    mutate(msg, types)
    with pytest.raises(ValueError, match=message):
        camera_info_to_model(msg)


def test_odometry_round_trip_rotates_twist_into_body(types):
    T = random_pose(1)
    v_w = np.array([1.0, -2.0, 0.5])
    cov = np.diag(np.arange(1, 7, dtype=np.float64))
    msg = pose_to_odometry(types, 77, T, "odom", "base_link", velocity_world=v_w,
                           angular_velocity_body=[0.1, 0.2, 0.3], pose_covariance=cov)
    msg = cdr_round_trip(types, msg, "nav_msgs/msg/Odometry")
    np.testing.assert_allclose([msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z],
                               T[:3, :3].T @ v_w, atol=1e-12)
    out = odometry_to_pose(msg)
    assert (out["t_ns"], out["frame_id"], out["child_frame_id"]) == (77, "odom", "base_link")
    np.testing.assert_allclose(out["T"], T, atol=1e-12)
    np.testing.assert_allclose(out["velocity_world"], v_w, atol=1e-12)
    np.testing.assert_allclose(out["pose_covariance"], cov)


def test_odometry_batch_matches_the_checked_builder(types):
    """IMU-rate odometry builds its messages unchecked, in a batch: the same messages as one by one."""
    T = np.stack([random_pose(s) for s in range(3)])
    v_w = np.array([[1.0, -2.0, 0.5], [0.0, 0.3, 0.1], [2.0, 0.0, -1.0]])
    cov = np.diag(np.arange(1, 7, dtype=np.float64))
    batch = odometry_messages(types, [5, 6, 7_000_000_001], T, "map", "base_link", velocity_world=v_w,
                              angular_velocity_body=[0.1, 0.2, 0.3], twist_covariance=cov)
    for k, msg in enumerate(batch):
        one = pose_to_odometry(types, [5, 6, 7_000_000_001][k], T[k], "map", "base_link", velocity_world=v_w[k],
                               angular_velocity_body=[0.1, 0.2, 0.3], twist_covariance=cov)
        a, b = (odometry_to_pose(cdr_round_trip(types, m, "nav_msgs/msg/Odometry")) for m in (msg, one))
        assert (a["t_ns"], a["frame_id"], a["child_frame_id"]) == (b["t_ns"], "map", "base_link")
        for key in ("T", "velocity_world", "angular_velocity_body", "pose_covariance", "twist_covariance"):
            np.testing.assert_allclose(a[key], b[key], atol=1e-12)
        np.testing.assert_allclose(a["T"], T[k], atol=1e-12)


def test_malformed_odometry_raises(types):
    msg = pose_to_odometry(types, 0, np.eye(4), "odom", "base_link")
    msg.pose.pose.orientation.w = 0.0
    with pytest.raises(ValueError, match="unit quaternion"):
        odometry_to_pose(msg)
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="rigid transform"):
        pose_to_odometry(types, 0, bad, "odom", "base_link")
    with pytest.raises(ValueError, match=">= 0 ns"):
        pose_to_odometry(types, -1, np.eye(4), "odom", "base_link")


def test_path_round_trip(types):
    poses = np.stack([random_pose(s) for s in range(5)])
    quat = np.array([[q[3], q[0], q[1], q[2]] for q in (matrix_to_quat_xyzw(T[:3, :3]) for T in poses)])
    traj = Trajectory(np.arange(5) * 50_000_000, poses[:, :3, 3], quat)
    msg = cdr_round_trip(types, trajectory_to_path(types, traj, "map"), "nav_msgs/msg/Path")
    assert msg.header.frame_id == "map" and len(msg.poses) == 5
    back = path_to_trajectory(msg)
    np.testing.assert_array_equal(back.t_ns, traj.t_ns)
    np.testing.assert_allclose(back.matrices(), poses, atol=1e-9)
    # the batched builder of a node's path gives the same message content
    fast = cdr_round_trip(types, poses_to_path(types, traj.t_ns, poses, "map", 7), "nav_msgs/msg/Path")
    assert fast.header.frame_id == "map" and stamp_to_ns(fast.header.stamp) == 7
    np.testing.assert_array_equal(path_to_trajectory(fast).t_ns, traj.t_ns)
    np.testing.assert_allclose(path_to_trajectory(fast).matrices(), poses, atol=1e-9)


def test_a_keyframe_path_rebuilds_only_what_moved(types):
    """The node's path keeps each keyframe's pose message until the keyframe moves: the message after any mix of
    new, moved and evicted keyframes is the one built from scratch of the newest ``max_poses``, in id order."""
    poses = {k: random_pose(k) for k in range(8)}
    stamps = {k: 1_000_000 * (k + 1) for k in range(8)}
    path = KeyframePath(types, "map", max_poses=5)

    def put(ids):
        path.set(ids, np.array([stamps[k] for k in ids]), np.stack([poses[k] for k in ids]))

    def check(ids):
        msg = cdr_round_trip(types, path.message(9), "nav_msgs/msg/Path")
        ref = path_to_trajectory(poses_to_path(types, np.array([stamps[k] for k in ids]),
                                               np.stack([poses[k] for k in ids]), "map", 9))
        back = path_to_trajectory(msg)
        assert msg.header.frame_id == "map" and stamp_to_ns(msg.header.stamp) == 9
        np.testing.assert_array_equal(back.t_ns, ref.t_ns)
        np.testing.assert_allclose(back.matrices(), ref.matrices(), atol=1e-12)

    put([0, 1, 3])
    check([0, 1, 3])
    kept = path.message(0).poses[0]
    poses[1] = random_pose(11)
    put([1, 2])                 # one moved, one new between kept ones
    check([0, 1, 2, 3])
    assert path.message(0).poses[0] is kept   # keyframe 0 did not move: its message was not rebuilt
    put([4, 5, 6])              # past max_poses: the oldest fall off
    check([2, 3, 4, 5, 6])
    poses[0] = random_pose(10)
    put([0])                    # older than the whole path now: left out
    check([2, 3, 4, 5, 6])
    assert len(path) == 5
    with pytest.raises(ValueError, match="max_poses >= 1"):
        KeyframePath(types, "map", 0)


def test_tf_message_round_trip(types):
    transforms = [StampedTransform(10, "map", "odom", random_pose(3)),
                  StampedTransform(10, "odom", "base_link", random_pose(4))]
    msg = cdr_round_trip(types, tf_message(types, transforms), "tf2_msgs/msg/TFMessage")
    back = tf_message_to_transforms(msg)
    assert [(b.parent, b.child, b.t_ns) for b in back] == [("map", "odom", 10), ("odom", "base_link", 10)]
    for a, b in zip(transforms, back):
        np.testing.assert_allclose(b.T, a.T, atol=1e-12)


def test_malformed_tf_raises(types):
    with pytest.raises(ValueError, match="distinct non-empty frames"):
        transform_stamped(types, np.eye(4), 0, "map", "map")
    msg = transform_stamped(types, np.eye(4), 0, "map", "odom")
    msg.child_frame_id = ""
    with pytest.raises(ValueError, match="empty frame id"):
        tf_message_to_transforms(types.new("tf2_msgs/msg/TFMessage", transforms=[msg]))
