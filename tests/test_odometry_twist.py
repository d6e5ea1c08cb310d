"""/odometry's twist on the shipped sample, through the frontend node's engine as the node publishes it (the
pose callback before the keyframe work): the body-frame linear velocity against the ground truth's, the angular
velocity against the ground-truth orientation's rate, and the node's constant twist covariance against the errors
(normalised error squared per degree of freedom, NEES/dof, within ``NEES_BAND``); and the pose covariance's
drift model (:mod:`vigs_core.vio.odometry_covariance`) against the pose's error since the first metric frame.

Measured (one run): linear velocity 0.020 m/s rms per axis (the sample moves at 0.37 m/s on average), angular
velocity 0.029 / 0.067 / 0.050 rad/s rms (x / y / z, against a rate differentiated over +-10 ms of ground truth).
Frames before the IMU initialisation get no twist (the node publishes zero with the unknown covariance).
"""
from __future__ import annotations

import numpy as np
import pytest
from ros_bags import SAMPLE_BAG
from scipy.spatial.transform import Rotation

from vigs_core.eval.odometry_consistency import drift_errors, nees
from vigs_core.system import PipelineConfig
from vigs_core.system.pipeline import poses_to_trajectory
from vigs_core.system.sources import open_input
from vigs_core.vio.odometry import METRIC_STATUSES
from vigs_core.vio.odometry_covariance import OdometryCovariance, OdometryCovarianceConfig
from vigs_ros.frontend_engine import FrontendEngine

DEFAULTS = OdometryCovarianceConfig()
VELOCITY_RMS_MAX = 0.04      # m/s per axis
ANGULAR_RMS_MAX = 0.1        # rad/s per axis
NEES_BAND = (0.1, 2.0)
POSE_NEES_BAND = (0.02, 1.5)  # the drift model is calibrated to be conservative (docs/benchmarks.md)


def ground_truth_twist(gt, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame velocity and angular rate of the ground truth at ``t_ns`` (rate over +-2 samples)."""
    i = min(int(np.searchsorted(gt.t_ns, t_ns)), len(gt.t_ns) - 1)
    rot = lambda k: Rotation.from_quat(gt.quat_wxyz[k][[1, 2, 3, 0]])   # noqa: E731
    i0, i1 = max(i - 2, 0), min(i + 2, len(gt.t_ns) - 1)
    rate = (rot(i0).inv() * rot(i1)).as_rotvec() / ((gt.t_ns[i1] - gt.t_ns[i0]) * 1e-9)
    return rot(i).as_matrix().T @ gt.velocity[i], rate


@pytest.fixture(scope="module")
def twists():
    seq = open_input(SAMPLE_BAG)
    engine = FrontendEngine(seq.camera, PipelineConfig(), seq.T_BS, seq.imu_noise)
    imu, k, rows, poses, frames = seq.imu, 0, [], [], 0
    for t_ns, image in seq.frames():
        while k < len(imu) and not engine.stream.imu.covers(t_ns):
            engine.stream.add_imu(int(imu.t_ns[k]), imu.gyro[k], imu.acc[k])
            k += 1

        def on_pose(T_wc, t_ns=t_ns):
            poses.append((t_ns, engine.status, T_wc @ np.linalg.inv(seq.T_BS)))
            twist = engine.body_twist(t_ns, T_wc)
            if twist is not None:
                rows.append((t_ns, engine.status, *twist, *ground_truth_twist(seq.groundtruth, t_ns)))

        engine.track(t_ns, image, "mono8", on_pose)
        frames += 1
    return rows, frames, poses, seq.groundtruth


def test_the_twist_follows_the_ground_truth_once_metric(twists):
    rows, frames, _, _ = twists
    assert 150 < len(rows) < frames            # the frames after the IMU initialisation (measured: 228 of 441)
    assert {status for _, status, *_ in rows} == {"tracking"}
    v_err = np.array([v - v_gt for _, _, v, _, v_gt, _ in rows])
    w_err = np.array([w - w_gt for _, _, _, w, _, w_gt in rows])
    assert np.sqrt((v_err ** 2).mean(0)).max() < VELOCITY_RMS_MAX
    assert np.sqrt((w_err ** 2).mean(0)).max() < ANGULAR_RMS_MAX
    speeds = np.linalg.norm([v_gt for *_, v_gt, _ in rows], axis=1)
    assert speeds.mean() > 5 * VELOCITY_RMS_MAX   # the platform moves: a zero twist would fail


def test_the_twist_covariance_is_consistent_with_the_errors(twists):
    rows, _, _, _ = twists
    v_err = np.array([v - v_gt for _, _, v, _, v_gt, _ in rows])
    w_err = np.array([w - w_gt for _, _, _, w, _, w_gt in rows])
    nees_v = float((v_err ** 2).mean() / DEFAULTS.velocity_std ** 2)
    nees_w = float((w_err ** 2).mean() / DEFAULTS.angular_velocity_std ** 2)
    assert NEES_BAND[0] < nees_v < NEES_BAND[1], nees_v
    assert NEES_BAND[0] < nees_w < NEES_BAND[1], nees_w


def test_the_pose_covariance_grows_with_the_path_and_is_consistent_with_the_error(twists):
    """The published pose covariance (the drift model fed every frame as the node does) against the body pose's
    error since the first metric frame: NEES per degree of freedom within POSE_NEES_BAND, growing with the
    distance travelled."""
    _, _, poses, gt = twists
    model = OdometryCovariance()
    covariances = np.stack([model.pose(T[:3, 3], status) for _, status, T in poses])
    metric = np.array([status in METRIC_STATUSES for _, status, _ in poses])
    assert metric.sum() > 150 and model.distance > 2.0, (metric.sum(), model.distance)
    est = poses_to_trajectory(np.array([t for t, _, _ in poses]), np.stack([T for _, _, T in poses]))
    errors = drift_errors(gt, est, metric, max_diff_s=1e-3)
    assert len(errors.t_ns) == metric.sum()
    C = covariances[metric]
    assert C[-1, 0, 0] > C[0, 0, 0] and C[-1, 5, 5] > C[0, 5, 5]
    np.testing.assert_allclose(np.sqrt(np.diag(covariances[~metric][0])), [DEFAULTS.unknown_std] * 6)
    per_dof = float(nees(errors, C).mean() / 6)
    print(f"pose NEES per dof {per_dof:.3f} over {metric.sum()} frames, {model.distance:.2f} m")
    assert POSE_NEES_BAND[0] < per_dof < POSE_NEES_BAND[1], per_dof
    # against the error alone, the same model fed a tenth of its standard deviations is overconfident
    tight = OdometryCovariance(OdometryCovarianceConfig(**{k: v / 10 for k, v in vars(DEFAULTS).items()}))
    tight_C = np.stack([tight.pose(T[:3, 3], status) for _, status, T in poses])[metric]
    assert nees(errors, tight_C).mean() / 6 > POSE_NEES_BAND[1]


def test_the_drift_model_counts_metric_motion_only_and_restarts():
    model, c = OdometryCovariance(), DEFAULTS
    unknown = model.pose(np.zeros(3), "initialising")
    np.testing.assert_allclose(np.diag(unknown), [c.unknown_std ** 2] * 6)
    first = model.pose(np.array([1.0, 0, 0]), "tracking")   # the first metric frame: the start term only
    np.testing.assert_allclose(np.diag(first), [c.position_std ** 2] * 3 + [c.tilt_std ** 2] * 2 + [c.yaw_std ** 2])
    model.pose(np.array([4.0, 0, 0]), "tracking")
    model.pose(np.array([4.0, 4, 0]), "lost")               # not counted, and no jump after it
    C = model.pose(np.array([4.0, 3, 0]), "reinitialised")
    assert model.distance == 3.0
    r, d = np.sqrt(18.0), 3.0   # from the first metric position (1, 0, 0) to (4, 3, 0); metric path 3 m
    expected = c.position_std ** 2 + (c.scale_std * r) ** 2 + (c.position_drift * d) ** 2
    np.testing.assert_allclose(C[0, 0], expected)
    np.testing.assert_allclose(C[5, 5], c.yaw_std ** 2 + (c.yaw_drift * d) ** 2)
    model.restart()
    np.testing.assert_allclose(model.pose(np.array([9.0, 9, 9]), "tracking"), first)
