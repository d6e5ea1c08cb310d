"""The VIGS interface package: importable in rclpy, registered in rosbags with the same type hashes,
and every custom message adapter round-trips through CDR; malformed messages raise ValueError."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from adapters_helpers import cdr_round_trip, types  # noqa: F401  (types is a fixture)

from msg_adapters.types import RosbagsTypes
from msg_adapters.vigs import (
    GaussianDeltaData,
    KeyframeData,
    NavStateData,
    PoseUpdateData,
    PreintegrationData,
    gaussian_delta_to_msg,
    keyframe_to_msg,
    msg_to_gaussian_delta,
    msg_to_keyframe,
    msg_to_nav_state,
    msg_to_pose_update,
    msg_to_preintegration,
    nav_state_to_msg,
    pose_update_to_msg,
    preintegration_to_msg,
)
from vigs_core.camera import CameraModel

VIGS_TYPES = ["Keyframe", "NavState", "PreintegratedImu", "KeyframePoseUpdate", "GaussianDelta"]


def pose(tx: float) -> np.ndarray:
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [tx, 2.0, -1.0]
    return T


def test_interface_package_imports_in_rclpy_and_hashes_match_rosbags():
    import tf2_msgs.msg
    import vigs_msgs.msg

    store = RosbagsTypes().typestore
    for name in VIGS_TYPES:
        assert hasattr(vigs_msgs.msg, name)
        desc = Path(sys.prefix) / "share" / "vigs_msgs" / "msg" / f"{name}.json"
        built = json.loads(desc.read_text())["type_hashes"][0]["hash_string"]
        assert built == store.hash_rihs01(f"vigs_msgs/msg/{name}")
    assert hasattr(tf2_msgs.msg, "TFMessage")
    tf_json = Path(sys.prefix) / "share" / "tf2_msgs" / "msg" / "TFMessage.json"
    assert json.loads(tf_json.read_text())["type_hashes"][0]["hash_string"] == store.hash_rihs01(
        "tf2_msgs/msg/TFMessage")


def make_keyframe(with_disparity: bool = True) -> KeyframeData:
    rng = np.random.default_rng(0)
    camera = CameraModel(16, 12, 20.0, 21.0, 7.5, 5.5)
    return KeyframeData(
        id=7, t_ns=1_403_636_580_013_555_456, T_wc=pose(1.0),
        image=rng.integers(0, 256, (12, 16), dtype=np.uint8), encoding="mono8", camera=camera,
        disparity=rng.uniform(0.1, 2.0, (3, 4)).astype(np.float32) if with_disparity else None,
    )


@pytest.mark.parametrize("with_disparity,metric", [(True, False), (False, True)])
def test_keyframe_round_trip(types, with_disparity, metric):
    kf = make_keyframe(with_disparity)
    kf.metric = metric
    back = msg_to_keyframe(cdr_round_trip(types, keyframe_to_msg(types, kf), "vigs_msgs/msg/Keyframe"))
    assert (back.id, back.t_ns, back.encoding, back.camera, back.metric) == (kf.id, kf.t_ns, kf.encoding, kf.camera,
                                                                              metric)
    np.testing.assert_allclose(back.T_wc, kf.T_wc, atol=1e-12)
    np.testing.assert_array_equal(back.image, kf.image)
    if with_disparity:
        np.testing.assert_array_equal(back.disparity, kf.disparity)
    else:
        assert back.disparity is None


def test_keyframe_rclpy_bytes_deserialize_in_rosbags():
    from msg_adapters.types import RclpyTypes

    rc, rb = RclpyTypes(), RosbagsTypes()
    kf = make_keyframe()
    data = rc.serialize(keyframe_to_msg(rc, kf), "vigs_msgs/msg/Keyframe")
    back = msg_to_keyframe(rb.deserialize(data, "vigs_msgs/msg/Keyframe"))
    np.testing.assert_array_equal(back.image, kf.image)


def test_malformed_keyframe_raises(types):
    kf = make_keyframe()
    msg = keyframe_to_msg(types, kf)
    msg.camera_info.width = 20
    with pytest.raises(ValueError, match="camera_info is 20x12"):
        msg_to_keyframe(msg)
    kf.camera = CameraModel(10, 12, 20.0, 21.0, 5, 5)
    with pytest.raises(ValueError, match="image is 16x12 but camera is 10x12"):
        keyframe_to_msg(types, kf)


def test_nav_state_round_trip(types):
    s = NavStateData(123, 4, pose(0.5), np.array([0.1, 0.2, 0.3]), np.array([1e-3, 0, 0]),
                     np.array([0, 0.01, 0]), True)
    back = msg_to_nav_state(cdr_round_trip(types, nav_state_to_msg(types, s), "vigs_msgs/msg/NavState"))
    assert (back.t_ns, back.keyframe_id, back.inertial_initialized) == (123, 4, True)
    np.testing.assert_allclose(back.T_wb, s.T_wb, atol=1e-12)
    np.testing.assert_allclose(back.bias_acc, s.bias_acc)


def make_preintegration() -> PreintegrationData:
    rng = np.random.default_rng(1)
    A = rng.standard_normal((9, 9))
    return PreintegrationData(
        from_id=3, to_id=4, start_ns=1_000_000_000, end_ns=1_250_000_000, num_samples=50,
        delta_R=pose(0)[:3, :3], delta_v=np.array([0.1, 0, 2.4]), delta_p=np.array([0.01, 0, 0.3]),
        covariance=A @ A.T, jacobians={k: rng.standard_normal((3, 3)) for k in (
            "d_rotation_d_gyro_bias", "d_velocity_d_gyro_bias", "d_velocity_d_acc_bias",
            "d_position_d_gyro_bias", "d_position_d_acc_bias")},
        bias_gyro=np.array([1e-3, 2e-3, 3e-3]), bias_acc=np.array([0.01, 0.02, 0.03]),
    )


def test_preintegrated_imu_round_trip(types):
    p = make_preintegration()
    msg = cdr_round_trip(types, preintegration_to_msg(types, p), "vigs_msgs/msg/PreintegratedImu")
    assert msg.dt == pytest.approx(0.25)
    back = msg_to_preintegration(msg)
    assert (back.from_id, back.to_id, back.num_samples, back.dt) == (3, 4, 50, 0.25)
    np.testing.assert_allclose(back.covariance, p.covariance)
    for k, v in p.jacobians.items():
        np.testing.assert_allclose(back.jacobians[k], v)
    np.testing.assert_allclose(back.delta_R, p.delta_R)


def test_malformed_preintegrated_imu_raises(types):
    msg = preintegration_to_msg(types, make_preintegration())
    msg.dt = 1.0
    with pytest.raises(ValueError, match="disagrees"):
        msg_to_preintegration(msg)
    msg = preintegration_to_msg(types, make_preintegration())
    cov = np.array(msg.covariance).reshape(9, 9)
    cov[0, 1] += 1.0
    msg.covariance = cov.reshape(-1)
    with pytest.raises(ValueError, match="not symmetric"):
        msg_to_preintegration(msg)
    p = make_preintegration()
    p.end_ns = 0
    with pytest.raises(ValueError, match="before start"):
        preintegration_to_msg(types, p)


def test_pose_update_round_trip_and_malformed(types):
    u = PoseUpdateData(9, np.array([1, 5, 8]), np.stack([pose(0), pose(1), pose(2)]), np.array([1.0, 1.1, 0.9]))
    back = msg_to_pose_update(cdr_round_trip(types, pose_update_to_msg(types, u), "vigs_msgs/msg/KeyframePoseUpdate"))
    np.testing.assert_array_equal(back.ids, u.ids)
    np.testing.assert_allclose(back.poses, u.poses, atol=1e-12)
    np.testing.assert_allclose(back.scales, u.scales)
    msg = pose_update_to_msg(types, u)
    msg.scales = types.sequence([1.0, 1.0], np.float64)
    with pytest.raises(ValueError, match="3 ids, 3 poses, 2 scales"):
        msg_to_pose_update(msg)
    u.scales = np.array([1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="finite and > 0"):
        pose_update_to_msg(types, u)


def make_delta(n_added=3, n_changed=2) -> GaussianDeltaData:
    rng = np.random.default_rng(2)
    n = n_added + n_changed
    q = rng.standard_normal((n, 4))
    return GaussianDeltaData(
        t_ns=5, version=12, added_ids=np.arange(n_added) + 100, changed_ids=np.arange(n_changed) + 10,
        removed_ids=np.array([1, 2]), means=rng.standard_normal((n, 3)), rotations=q / np.linalg.norm(q, axis=1,
                                                                                                          keepdims=True),
        scales=rng.uniform(0.01, 0.1, (n, 3)), opacities=rng.uniform(0, 1, n),
        colors=rng.uniform(0, 1, (n, 3)), anchor_keyframe_ids=rng.integers(0, 5, n),
    )


def test_gaussian_delta_round_trip(types):
    d = make_delta()
    back = msg_to_gaussian_delta(cdr_round_trip(types, gaussian_delta_to_msg(types, d), "vigs_msgs/msg/GaussianDelta"))
    assert back.version == 12 and back.colors.shape == (5, 3)
    np.testing.assert_array_equal(back.removed_ids, d.removed_ids)
    np.testing.assert_allclose(back.means, d.means, rtol=1e-6)
    np.testing.assert_allclose(back.colors, d.colors, rtol=1e-6)
    np.testing.assert_array_equal(back.anchor_keyframe_ids, d.anchor_keyframe_ids)


def test_malformed_gaussian_delta_raises(types):
    msg = gaussian_delta_to_msg(types, make_delta())
    msg.means = types.sequence(np.zeros(14), np.float32)
    with pytest.raises(ValueError, match="means has 14 values, expected 5 rows x 3"):
        msg_to_gaussian_delta(msg)
    d = make_delta()
    d.opacities = d.opacities + 2.0
    with pytest.raises(ValueError, match=r"opacities must lie in \[0, 1\]"):
        gaussian_delta_to_msg(types, d)
    msg = gaussian_delta_to_msg(types, make_delta())
    msg.colors = types.sequence(np.full(15, 2.0), np.float32)
    with pytest.raises(ValueError, match=r"colors must lie in \[0, 1\]"):
        msg_to_gaussian_delta(msg)
