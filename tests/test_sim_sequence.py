"""Simulated sequences end to end: hybrid and procedural sources, `vigs sim`, ASL round trip through the
project's EuRoC reader, byte-identical output for the same seed and arguments."""
from pathlib import Path

import numpy as np
import pytest
import torch

from vigs_cli.main import main
from vigs_core.io import EurocSequence, read_euroc_groundtruth, read_euroc_imu, read_tum
from vigs_core.sim.degrade import DegradeConfig
from vigs_core.sim.hybrid import SimConfig, SimSequence, euroc_cam0_calibration, hybrid_source
from vigs_core.sim.writers import read_depth

torch.set_num_threads(1)

EXCERPT = Path(__file__).parent / "data" / "sim_hybrid_excerpt"
SMALL = ["--width", "94", "--no-progress"]


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_hybrid_sequence_uses_real_imu_and_ground_truth_poses():
    imu = read_euroc_imu(EXCERPT / "mav0/imu0/data.csv")
    gt = read_euroc_groundtruth(EXCERPT / "mav0/state_groundtruth_estimate0/data.csv")
    cal = euroc_cam0_calibration()
    seq = SimSequence(hybrid_source(gt, imu), cal.camera.scaled(0.125), cal.T_BS, SimConfig(duration_s=0.5))
    assert len(seq) == 11 and np.all(np.diff(seq.frame_t_ns) == 50_000_000)
    # real IMU passed through unchanged over the frames' span (one sample period of margin)
    assert seq.imu.t_ns[0] <= seq.frame_t_ns[0] and seq.imu.t_ns[-1] >= seq.frame_t_ns[-1]
    inside = (imu.t_ns >= seq.imu.t_ns[0]) & (imu.t_ns <= seq.imu.t_ns[-1])
    np.testing.assert_array_equal(seq.imu.acc, imu.acc[inside])
    # frames on ground-truth stamps get exactly the ground-truth camera pose T_WB T_BS
    frame = next(seq.frames())
    k = int(np.searchsorted(gt.t_ns, frame.t_ns))
    assert gt.t_ns[k] == frame.t_ns
    np.testing.assert_allclose(frame.T_WC, gt.matrices()[k] @ cal.T_BS, atol=1e-12)
    assert frame.image.dtype == np.uint8 and frame.depth.dtype == np.float32


def test_sub_frame_averaging_blurs_moving_frames():
    imu = read_euroc_imu(EXCERPT / "mav0/imu0/data.csv")
    gt = read_euroc_groundtruth(EXCERPT / "mav0/state_groundtruth_estimate0/data.csv")
    cal = euroc_cam0_calibration()
    cam = cal.camera.scaled(0.25)
    sharp = SimSequence(hybrid_source(gt, imu), cam, cal.T_BS, SimConfig(duration_s=0.2)).render_frame(2)
    config = SimConfig(duration_s=0.2, degrade=DegradeConfig(exposure_time_s=0.1, blur_subframes=8))
    blurred = SimSequence(hybrid_source(gt, imu), cam, cal.T_BS, config).render_frame(2)
    energy = lambda im: np.mean(np.diff(im.astype(np.float64), axis=1) ** 2)  # noqa: E731
    assert energy(blurred.image) < 0.8 * energy(sharp.image)
    np.testing.assert_array_equal(blurred.depth, sharp.depth)  # depth at the stamp's pose


def test_vigs_sim_asl_round_trip_and_determinism(tmp_path):
    args = ["sim", "--trajectory", str(EXCERPT / "mav0/state_groundtruth_estimate0/data.csv"),
            "--imu", str(EXCERPT / "mav0/imu0/data.csv"), "--duration", "0.6", "--read-noise", "2", *SMALL]
    assert main([*args, "--asl", str(tmp_path / "a")]) == 0
    assert main([*args, "--asl", str(tmp_path / "b")]) == 0
    first, second = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert first.keys() == second.keys() and first == second  # byte-identical
    seq = EurocSequence(tmp_path / "a")
    assert len(seq.frame_t_ns) == 13
    assert seq.camera_calibration.camera.width == 94 and seq.camera_calibration.camera.height == 60
    np.testing.assert_allclose(seq.camera_calibration.T_BS, euroc_cam0_calibration().T_BS)
    real = read_euroc_imu(EXCERPT / "mav0/imu0/data.csv")
    inside = (real.t_ns >= seq.imu.t_ns[0]) & (real.t_ns <= seq.imu.t_ns[-1])
    np.testing.assert_array_equal(seq.imu.gyro, real.gyro[inside])
    gt = seq.groundtruth
    assert gt.velocity is not None and gt.t_ns[0] <= seq.frame_t_ns[0] and gt.t_ns[-1] >= seq.frame_t_ns[-1]
    tum = read_tum(tmp_path / "a" / "groundtruth_tum.txt")
    np.testing.assert_array_equal(tum.t_ns, gt.t_ns)
    import cv2

    image = cv2.imread(str(seq.frame_paths[3]), cv2.IMREAD_UNCHANGED)
    assert image.shape == (60, 94) and image.dtype == np.uint8 and image.std() > 10
    depth = read_depth(tmp_path / "a" / "mav0" / "depth0" / "data" / f"{seq.frame_t_ns[3]}.tiff")
    assert depth.shape == (60, 94) and depth.min() > 0.1


def test_vigs_sim_procedural_with_synthesised_imu_and_seeds(tmp_path):
    base = ["sim", "--procedural", "--procedural-duration", "2", "--duration", "0.3", "--no-depth", *SMALL]
    assert main([*base, "--asl", str(tmp_path / "a")]) == 0
    assert main([*base, "--seed", "1", "--asl", str(tmp_path / "b")]) == 0
    a, b = EurocSequence(tmp_path / "a"), EurocSequence(tmp_path / "b")
    assert len(a.frame_t_ns) == 7 and len(a.imu) >= 60
    assert not (tmp_path / "a" / "mav0" / "depth0").exists()
    assert a.groundtruth.bias_gyro is not None
    # at rest the accelerometer would read +g; along the gentle procedural motion its norm stays near g
    assert np.abs(np.linalg.norm(a.imu.acc, axis=1) - 9.81).max() < 3.0
    assert _files(tmp_path / "a") != _files(tmp_path / "b")  # another scene seed, another sequence


def test_vigs_sim_procedural_speed_runs_the_same_path_faster(tmp_path):
    base = ["sim", "--procedural", "--procedural-duration", "2", "--no-depth", "--noise-free-imu", *SMALL]
    assert main([*base, "--duration", "0.6", "--asl", str(tmp_path / "x1")]) == 0
    assert main([*base, "--duration", "0.3", "--procedural-speed", "2", "--asl", str(tmp_path / "x2")]) == 0
    a, b = (read_tum(tmp_path / name / "groundtruth_tum.txt") for name in ("x1", "x2"))
    ta, tb = (a.t_ns - a.t_ns[0]) * 1e-9, (b.t_ns - b.t_ns[0]) * 1e-9
    inside = 2 * tb <= ta[-1]
    for k in range(3):   # the speed-2 path at t is the speed-1 path at 2 t
        assert np.allclose(b.position[inside, k], np.interp(2 * tb[inside], ta, a.position[:, k]), atol=1e-4)
    assert np.linalg.norm(np.diff(b.position, axis=0), axis=1).sum() > 1.9 * np.linalg.norm(
        np.diff(a.position[ta <= 0.3], axis=0), axis=1).sum()
    ia, ib = EurocSequence(tmp_path / "x1").imu, EurocSequence(tmp_path / "x2").imu
    rate_a = np.interp(2 * (ib.t_ns - ib.t_ns[0]) * 1e-9, (ia.t_ns - ia.t_ns[0]) * 1e-9, np.linalg.norm(ia.gyro, axis=1))
    assert np.allclose(np.linalg.norm(ib.gyro, axis=1)[:50], 2 * rate_a[:50], rtol=0.02, atol=1e-3)
    assert main([*base, "--procedural-speed", "0", "--asl", str(tmp_path / "x0")]) == 2


def test_vigs_sim_rejects_bad_arguments(tmp_path, capsys):
    assert main(["sim", "--procedural", "--no-progress"]) == 2
    assert "--asl" in capsys.readouterr().err
    assert main(["sim", "--asl", str(tmp_path / "x"), "--no-progress"]) == 2
    with pytest.raises(ValueError, match="empty time range"):
        main(["sim", "--procedural", "--procedural-duration", "1", "--start", "5", "--asl", str(tmp_path / "y"),
              *SMALL])


def test_vigs_sim_bag_output_is_byte_identical_and_readable(tmp_path):
    from vigs_core.io.rosbag import read_bag

    args = ["sim", "--euroc", str(EXCERPT), "--duration", "0.3", "--image-format", "png", *SMALL]
    for name in ("a", "b"):
        assert main([*args, "--bag", str(tmp_path / name / "bag")]) == 0
    for f in ("bag/bag.mcap", "bag/metadata.yaml", "bag_groundtruth_tum.txt"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    rec = read_bag(tmp_path / "a" / "bag")
    assert rec.image_count == 7 and rec.depth_topic == "/cam0/depth" and rec.camera.width == 94
    gt = read_tum(tmp_path / "a" / "bag_groundtruth_tum.txt")
    np.testing.assert_array_equal(gt.t_ns, rec.groundtruth.t_ns)


def test_vigs_sim_photo_textures_change_the_images(tmp_path):
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        cv2.imwrite(str(photos / f"{k}.png"), rng.integers(0, 256, (48, 64), dtype=np.uint8))
    base = ["sim", "--euroc", str(EXCERPT), "--duration", "0.1", "--no-depth", *SMALL]
    assert main([*base, "--asl", str(tmp_path / "plain")]) == 0
    assert main([*base, "--photos", str(photos), "--asl", str(tmp_path / "photo")]) == 0
    plain, photo = EurocSequence(tmp_path / "plain"), EurocSequence(tmp_path / "photo")
    a = cv2.imread(str(plain.frame_paths[0]), cv2.IMREAD_UNCHANGED).astype(np.float64)
    b = cv2.imread(str(photo.frame_paths[0]), cv2.IMREAD_UNCHANGED).astype(np.float64)
    changed = np.abs(a - b) > 2
    assert 0.05 < changed.mean() < 0.95  # some surfaces carry photos, others keep their pattern
    assert main([*base, "--photos", str(tmp_path / "plain" / "mav0"), "--asl", str(tmp_path / "none")]) == 2
