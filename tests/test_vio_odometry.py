"""End to end: ``vigs run`` (dense visual-inertial odometry) on a rendered synthetic room with a noisy synthetic
IMU gives a metric, gravity-aligned trajectory with velocities; with fusion off it is the vision-only odometry."""
import json

import cv2
import numpy as np
import pytest
import torch

from vigs_core.camera import CameraModel
from vigs_core.eval import umeyama
from vigs_core.frontend.odometry import DenseOdometry, OdometryConfig
from vigs_core.geometry import matrix_to_quat, quat_to_matrix
from vigs_core.io import (CameraCalibration, write_camera_yaml, write_euroc_camera, write_euroc_groundtruth,
                          write_euroc_imu, write_imu_yaml)
from vigs_core.sim.imu_synthesis import imu_stamps, synthesize_imu
from vigs_core.sim.trajectory import ProceduralConfig, ProceduralMotion
from vigs_core.solver import Intrinsics
from vigs_core.types import Trajectory
from vigs_core.vio.config import VioConfig
from vigs_core.vio.odometry import VisualInertialOdometry
from vigs_cli.main import main as vigs_main
from vio_synthetic import NOISE, T_BC, BoxRoom

torch.set_num_threads(1)
FX, CX, CY, W, H = 115.0, 93.5, 59.5, 188, 120
BIAS_G, BIAS_A = np.array([0.003, -0.01, 0.02]), np.array([0.05, -0.08, 0.1])


@pytest.fixture(scope="module")
def room_sequence():
    duration = 8.0
    cfg = ProceduralConfig(duration_s=duration + 1, min_period_s=3.0, max_period_s=8.0, yaw_amplitude=0.5)
    motion = ProceduralMotion(0, T_BC[:3, :3].numpy(), cfg, start_ns=10**9)
    imu = synthesize_imu(motion, imu_stamps(motion.start_ns, motion.end_ns, 200.0), NOISE, seed=0,
                         initial_bias_gyro=BIAS_G, initial_bias_acc=BIAS_A).imu
    stamps = motion.start_ns + np.arange(int(duration * 20)) * 50_000_000
    state = motion.evaluate(stamps)
    T_wb = np.tile(np.eye(4), (len(stamps), 1, 1))
    T_wb[:, :3, :3], T_wb[:, :3, 3] = state.rotation, state.position
    room = BoxRoom()
    images = [room.render(T, FX, FX, CX, CY, W, H) for T in T_wb @ T_BC.numpy()]
    return stamps, images, imu, T_wb, state.velocity


def _run(odo, stamps, images, count=None):
    for k in range(len(stamps) if count is None else count):
        odo.process(int(stamps[k]), images[k])
    return odo


def _nearest(stamps_ns, t_s):
    """Index (N,) of the stamp nearest to each time t_s (N,) in seconds."""
    return np.abs(stamps_ns[None, :] * 1e-9 - t_s[:, None]).argmin(1)


def _write_asl(root, stamps, images, imu, T_wb):
    cam_dir = root / "mav0" / "cam0"
    for p, img in zip(write_euroc_camera(cam_dir, stamps), images):
        cv2.imwrite(str(p), img)
    camera = CameraModel(W, H, FX, FX, CX, CY)
    write_camera_yaml(cam_dir / "sensor.yaml", CameraCalibration(camera, T_BC.numpy(), 20.0))
    (root / "mav0" / "imu0").mkdir(parents=True)
    write_euroc_imu(root / "mav0" / "imu0" / "data.csv", imu)
    write_imu_yaml(root / "mav0" / "imu0" / "sensor.yaml", NOISE)
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    quat = matrix_to_quat(torch.from_numpy(T_wb[:, :3, :3])).numpy()
    write_euroc_groundtruth(gt_dir / "data.csv", Trajectory(stamps, T_wb[:, :3, 3], quat))


def test_vigs_run_gives_metric_gravity_aligned_trajectory(room_sequence, tmp_path):
    """``vigs run`` on an ASL folder with IMU: visual-inertial, metric (SE(3) ATE without scale correction),
    gravity-aligned, with velocities and the inertial report."""
    stamps, images, imu, T_wb, vel = room_sequence
    _write_asl(tmp_path / "seq", stamps, images, imu, T_wb)
    params = tmp_path / "p.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    width: {W}\n    height: {H}\n    imu:\n"
                      "      vision_only_keyframes: 5\n      inertial_init_keyframes: 10\n")
    out = tmp_path / "out"
    assert vigs_main(["run", str(tmp_path / "seq"), "--params", str(params), "--out", str(out),
                      "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    rep = report["vio"]
    assert rep["metric"] and rep["stage"] == "visual_inertial"
    assert report["accuracy_se3"]["ate_rmse"] < 0.1
    assert abs(report["accuracy"]["scale"] - 1.0) < 0.05
    traj = np.loadtxt(out / "trajectory.txt")        # t x y z qx qy qz qw, body poses
    idx = _nearest(stamps, traj[:, 0])
    # gravity-aligned: the rotation that best maps the estimated body orientations onto the z-up ground truth's
    # (chordal mean of R_gt R_est^T) turns about z only, within 1 deg
    R_est = quat_to_matrix(torch.from_numpy(traj[:, [7, 4, 5, 6]])).numpy()
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", T_wb[idx, :3, :3], R_est))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    assert np.degrees(np.arccos(min(1.0, R[2, 2]))) < 1.0
    # velocities (yaw-free checks: speed and vertical component), gyro bias
    v = np.loadtxt(out / "velocity.txt")
    ok = ~np.isnan(v[:, 1])
    assert ok.sum() > len(stamps) // 3
    gv = vel[_nearest(stamps, v[ok, 0])]
    assert np.abs(np.linalg.norm(v[ok, 1:], axis=1) - np.linalg.norm(gv, axis=1)).mean() < 0.05
    assert np.abs(v[ok, 3] - gv[:, 2]).mean() < 0.05
    assert np.abs(np.array(rep["bias_gyro"]) - BIAS_G).max() < 3e-3
    assert rep["imu_predictions"] > 0
    assert len(rep["scale_history"]) == 1 and rep["scale_history"][0]["stage"] == "aligned"
    assert len(rep["keyframe_states"]["velocity"]) == report["keyframes"]


def test_vio_without_fusion_is_the_vision_only_odometry(room_sequence):
    stamps, images, imu, _, _ = room_sequence
    intr = Intrinsics(FX, FX, CX, CY)
    a = _run(DenseOdometry(intr, W, H, OdometryConfig()), stamps, images, count=50)
    b = _run(VisualInertialOdometry(intr, W, H, imu, NOISE, T_BC, OdometryConfig(), VioConfig(enabled=False)),
             stamps, images, count=50)
    ta, Pa = a.final_frame_poses()
    tb, Pb = b.final_frame_poses()
    assert len(ta) > 20 and np.array_equal(ta, tb)
    assert torch.equal(Pa, Pb)
    assert b.report()["stage"] == "vision_only" and not b.report()["metric"]


def test_still_start_is_held_at_the_first_pose(room_sequence):
    """A camera standing still cannot initialise a monocular front end; the VI odometry holds it at the first
    frame's pose (no drift, no keyframes) instead of giving no pose."""
    stamps, images, imu, _, _ = room_sequence
    rng = np.random.default_rng(0)
    still = [np.clip(images[0] + rng.normal(0, 2, images[0].shape), 0, 255).astype(np.uint8) for _ in range(30)]
    intr = Intrinsics(FX, FX, CX, CY)
    odo = _run(VisualInertialOdometry(intr, W, H, imu, NOISE, T_BC, OdometryConfig(), VioConfig()), stamps, still,
               count=30)
    t, P = odo.final_frame_poses()
    assert np.array_equal(t, stamps[:30]) and len(odo.keyframes) == 0
    assert torch.equal(P, torch.eye(4, dtype=torch.float64).expand(30, 4, 4))
    assert odo.report()["held_still_frames"] == 30
    sent = []   # a live caller gets each held pose as it is given (on_pose)
    odo.process(int(stamps[30]), still[0], sent.append)
    assert len(sent) == 1 and torch.equal(sent[0], torch.eye(4, dtype=torch.float64))
    # with fusion off the behaviour is the front end's: no pose before initialisation
    off = _run(VisualInertialOdometry(intr, W, H, imu, NOISE, T_BC, OdometryConfig(), VioConfig(enabled=False)),
               stamps, still, count=30)
    assert len(off.final_frame_poses()[0]) == 0


def test_still_start_at_low_frame_rate_does_not_initialise_on_noise(room_sequence):
    """Frames 0.5 s apart (frame stride 10) from a camera standing still: the keyframe policy's interval
    (3 s) makes the front end try a two-view geometry on sub-pixel flow, which RANSAC fits; the front end rejects
    it (median flow below ``init_min_parallax_px``), so the VI odometry's frames stay held at the first pose and
    no keyframe exists, and the vision-only front end does not initialise either."""
    stamps, images, imu, _, _ = room_sequence
    rng = np.random.default_rng(1)
    still = [np.clip(images[0] + rng.normal(0, 2, images[0].shape), 0, 255).astype(np.uint8) for _ in range(16)]
    slow = stamps[0] + np.arange(16) * 500_000_000
    intr = Intrinsics(FX, FX, CX, CY)
    odo = _run(VisualInertialOdometry(intr, W, H, imu, NOISE, T_BC, OdometryConfig(), VioConfig()), slow, still)
    assert not odo.initialized and len(odo.keyframes) == 0
    assert odo.report()["held_still_frames"] == 16
    vo = _run(DenseOdometry(intr, W, H, OdometryConfig()), slow, still)
    assert not vo.initialized and len(vo.keyframes) == 0


def test_metric_windows_hold_the_fixed_keyframes_depth(room_sequence, monkeypatch):
    """Once metric (here at once: ``metric_hold_delay_s`` 0) every BA of the sliding window holds the fixed
    keyframe's disparities, none before; the trajectory stays metric. The room becomes metric about 0.4 s
    before its end, so only a few metric BAs run (at least the alignment's and the next keyframe's)."""
    import vigs_core.frontend.odometry as frontend
    stamps, images, imu, T_wb, _ = room_sequence
    calls = []

    def recording(*args, **kwargs):
        calls.append((odo.vio.metric, kwargs.get("fixed_disparity")))
        return bundle_adjust(*args, **kwargs)

    bundle_adjust = frontend.bundle_adjust
    monkeypatch.setattr(frontend, "bundle_adjust", recording)
    vio = VioConfig(vision_only_keyframes=5, inertial_init_keyframes=10, metric_hold_delay_s=0.0)
    odo = VisualInertialOdometry(Intrinsics(FX, FX, CX, CY), W, H, imu, NOISE, T_BC, OdometryConfig(), vio)
    _run(odo, stamps, images)
    assert odo.vio.metric
    metric = [hold for is_metric, hold in calls if is_metric]
    assert len(metric) >= 2 and all(h is not None and int(h.sum()) == 1 and bool(h[0]) for h in metric)
    assert all(hold is None for is_metric, hold in calls if not is_metric)
    t, T_cw = odo.final_frame_poses()
    p = (torch.linalg.inv(T_cw) @ torch.linalg.inv(T_BC))[:, :3, 3].numpy()   # body positions
    gt = T_wb[_nearest(stamps, t * 1e-9), :3, 3]
    s, R, tr = umeyama(p, gt, with_scale=True)
    _, R1, t1 = umeyama(p, gt, with_scale=False)
    assert abs(s - 1.0) < 0.05
    assert np.sqrt((((p @ R1.T + t1) - gt) ** 2).sum(1).mean()) < 0.1


def test_keyframes_that_left_the_window_drop_their_images_and_disparities(room_sequence):
    """Only window keyframes are matched and adjusted: the others' images and disparities are dropped at the next
    frame (loop closure and the mapper took them while the keyframes were in the window), so memory does not grow
    with every keyframe's pixels and depths; their revisions stay as the last BA left them."""
    stamps, images, _, _, _ = room_sequence
    odo = _run(DenseOdometry(Intrinsics(FX, FX, CX, CY), W, H, OdometryConfig()), stamps, images)
    window = set(odo.graph.keyframes)
    with_image = {k for k, kf in odo.keyframes.items() if kf.image is not None}
    with_disp = {k for k, kf in odo.keyframes.items() if kf.disp is not None}
    assert len(odo.keyframes) > len(window) + 2
    # those that left the window during the last frame's work keep theirs until the next frame
    assert window <= with_image and len(with_image - window) <= 1 and with_disp == with_image
    assert all(odo.keyframes[k].image.shape == (H, W) for k in window)
    assert all(kf.revision >= 1 for kf in odo.keyframes.values())   # every keyframe went through BA
