"""EuRoC ASL CSV readers/writers and the EurocSequence folder reader."""
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from vigs_core.camera import CameraModel
from vigs_core.io import (
    CameraCalibration,
    EurocSequence,
    MalformedFileError,
    read_euroc_camera,
    read_euroc_groundtruth,
    read_euroc_imu,
    write_camera_yaml,
    write_euroc_camera,
    write_euroc_groundtruth,
    write_euroc_imu,
    write_imu_yaml,
    write_tum,
)
from vigs_core.types import ImuNoise, ImuSamples, Trajectory

EXCERPT = Path(__file__).parent / "data" / "euroc_excerpt"
MAV0 = EXCERPT / "mav0"


def test_read_imu_excerpt():
    imu = read_euroc_imu(MAV0 / "imu0" / "data.csv")
    assert len(imu) == 40
    # First row of V1_01_easy imu0/data.csv.
    assert imu.t_ns[0] == 1403715273262142976
    np.testing.assert_allclose(imu.gyro[0], [-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824])
    np.testing.assert_allclose(imu.acc[0], [9.0874956666666655, 0.13075533333333333, -3.6938381666666662])
    assert np.all(np.diff(imu.t_ns) > 0)


def test_read_groundtruth_excerpt_with_velocity_and_biases():
    gt = read_euroc_groundtruth(MAV0 / "state_groundtruth_estimate0" / "data.csv")
    assert len(gt) == 80
    row = (MAV0 / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()[1].split(",")
    values = np.array([float(v) for v in row[1:]])
    assert gt.t_ns[0] == int(row[0])
    np.testing.assert_allclose(gt.position[0], values[0:3])
    np.testing.assert_allclose(gt.quat_wxyz[0], values[3:7] / np.linalg.norm(values[3:7]))
    np.testing.assert_allclose(gt.velocity[0], values[7:10])
    np.testing.assert_allclose(gt.bias_gyro[0], values[10:13])
    np.testing.assert_allclose(gt.bias_acc[0], values[13:16])


def test_imu_round_trip_exact(tmp_path):
    rng = np.random.default_rng(1)
    t_ns = 1403715273262142976 + 5_000_000 * np.arange(30)
    imu = ImuSamples(t_ns, rng.normal(size=(30, 3)), rng.normal(size=(30, 3)))
    write_euroc_imu(tmp_path / "imu0" / "data.csv", imu)
    back = read_euroc_imu(tmp_path / "imu0" / "data.csv")
    np.testing.assert_array_equal(back.t_ns, imu.t_ns)
    np.testing.assert_array_equal(back.gyro, imu.gyro)
    np.testing.assert_array_equal(back.acc, imu.acc)


def test_groundtruth_round_trip_full_and_pose_only(tmp_path):
    gt = read_euroc_groundtruth(MAV0 / "state_groundtruth_estimate0" / "data.csv")
    write_euroc_groundtruth(tmp_path / "full.csv", gt)
    back = read_euroc_groundtruth(tmp_path / "full.csv")
    np.testing.assert_array_equal(back.t_ns, gt.t_ns)
    for name in ("position", "quat_wxyz", "velocity", "bias_gyro", "bias_acc"):
        np.testing.assert_allclose(getattr(back, name), getattr(gt, name), rtol=0, atol=1e-15)
    pose_only = Trajectory(gt.t_ns, gt.position, gt.quat_wxyz)
    write_euroc_groundtruth(tmp_path / "pose.csv", pose_only)
    assert len((tmp_path / "pose.csv").read_text().splitlines()[1].split(",")) == 8
    back = read_euroc_groundtruth(tmp_path / "pose.csv")
    assert back.velocity is None and back.bias_gyro is None and back.bias_acc is None
    np.testing.assert_array_equal(back.t_ns, gt.t_ns)
    partial = Trajectory(gt.t_ns, gt.position, gt.quat_wxyz, velocity=gt.velocity)
    with pytest.raises(ValueError, match="has velocity but not bias_gyro, bias_acc"):
        write_euroc_groundtruth(tmp_path / "partial.csv", partial)


@pytest.mark.parametrize(
    "rows, line, fragment",
    [
        (["1000,0,0,0,0,0,9.8", "2000,0,0,0,0,9.8"], 3, "expected 7 columns like the first data row"),
        (["1000,0,0,0,0,0"], 2, "expected 7 columns (timestamp[ns], gyro"),
        (["1000,0,0,0,0,0,9.8", "2000.5,0,0,0,0,0,9.8"], 3, "must be integer nanoseconds, found '2000.5'"),
        (["1000,0,0,0,0,0,9.8", "2000,0,0,0,x,0,9.8"], 3, "column 5 must be a finite number"),
        (["1000,0,0,0,0,0,9.8", "1000,0,0,0,0,0,9.8"], 3, "repeats the stamp of line 2"),
    ],
)
def test_malformed_imu_csv(tmp_path, rows, line, fragment):
    path = tmp_path / "data.csv"
    path.write_text("#timestamp [ns],wx,wy,wz,ax,ay,az\n" + "\n".join(rows) + "\n")
    with pytest.raises(MalformedFileError) as info:
        read_euroc_imu(path)
    assert info.value.line == line
    assert str(path) in str(info.value)
    assert fragment in str(info.value)


def test_non_finite_imu_samples_are_left_out_with_a_warning(tmp_path):
    """A driver's invalid sample (nan / inf) is dropped, as the IMU node drops such a message; the other rows keep
    their own stamps; an unparsable value is still an error (test above)."""
    from vigs_core.io.text_table import SkippedRowsWarning

    path = tmp_path / "data.csv"
    path.write_text("#t\n1000,1,1,1,1,1,1\n2000,2,2,nan,2,2,2\n3000,3,3,3,3,3,3\n4000,4,4,4,inf,4,4\n5000,5,5,5,5,5,5\n")
    with pytest.warns(SkippedRowsWarning, match=r"2 rows with a non-finite value left out \(lines 3, 5\)"):
        imu = read_euroc_imu(path)
    np.testing.assert_array_equal(imu.t_ns, [1000, 3000, 5000])
    np.testing.assert_array_equal(imu.gyro[:, 0], [1, 3, 5])


def test_unsorted_rows_are_sorted(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("#t\n3000,3,3,3,3,3,3\n1000,1,1,1,1,1,1\n2000,2,2,2,2,2,2\n")
    imu = read_euroc_imu(path)
    np.testing.assert_array_equal(imu.t_ns, [1000, 2000, 3000])
    np.testing.assert_array_equal(imu.gyro[:, 0], [1, 2, 3])


def test_groundtruth_wrong_column_count(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("#t\n1000,0,0,0,1,0,0,0,0,0\n")
    with pytest.raises(MalformedFileError, match=r"line 2: expected 8 or 17 columns"):
        read_euroc_groundtruth(path)


def make_sequence(tmp_path: Path) -> Path:
    """A complete small ASL folder: the excerpt plus tiny PNG images for its 5 frames."""
    root = tmp_path / "V1_01_excerpt"
    shutil.copytree(EXCERPT, root)
    t_ns, _ = read_euroc_camera(root / "mav0" / "cam0", check_images=False)
    (root / "mav0" / "cam0" / "data").mkdir()
    for k, t in enumerate(t_ns):
        cv2.imwrite(str(root / "mav0" / "cam0" / "data" / f"{t}.png"), np.full((6, 8), 10 * k, np.uint8))
    return root


def test_camera_folder_and_missing_images(tmp_path):
    root = make_sequence(tmp_path)
    t_ns, paths = read_euroc_camera(root / "mav0" / "cam0")
    assert len(t_ns) == 5 and t_ns[0] == 1403715273262142976
    assert paths[0] == root / "mav0" / "cam0" / "data" / "1403715273262142976.png"
    assert cv2.imread(str(paths[2]), cv2.IMREAD_GRAYSCALE)[0, 0] == 20
    paths[1].unlink()
    paths[3].unlink()
    with pytest.raises(FileNotFoundError, match=r"2 of 5 images listed in .*data.csv are missing") as info:
        read_euroc_camera(root / "mav0" / "cam0")
    assert paths[1].name in str(info.value) and paths[3].name in str(info.value)
    # The shipped excerpt has stamps but, deliberately, no images.
    with pytest.raises(FileNotFoundError, match="5 of 5 images"):
        read_euroc_camera(MAV0 / "cam0")


def test_camera_csv_malformed(tmp_path):
    (tmp_path / "data.csv").write_text("#timestamp [ns],filename\n1000,a.png\n2000\n")
    with pytest.raises(MalformedFileError, match=r"line 3: expected 'timestamp\[ns\],filename'"):
        read_euroc_camera(tmp_path)


def test_euroc_sequence_bundles_everything(tmp_path):
    seq = EurocSequence(make_sequence(tmp_path))
    assert seq.name == "V1_01_excerpt"
    assert seq.has_camera and seq.has_groundtruth
    assert len(seq.frame_t_ns) == len(seq.frame_paths) == 5
    assert len(seq.imu) == 40
    assert seq.groundtruth.bias_acc.shape == (80, 3)
    cal = seq.camera_calibration
    assert (cal.camera.width, cal.camera.height, cal.camera.distortion) == (752, 480, "radtan")
    assert cal.rate_hz == 20.0
    np.testing.assert_allclose(cal.T_BS[0], [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975])
    assert seq.imu_noise.rate_hz == 200.0 and seq.imu_noise.gyro_noise_density == pytest.approx(1.6968e-04)
    np.testing.assert_array_equal(seq.imu_noise.T_BS, np.eye(4))
    # The mav0 folder itself is accepted as root too.
    assert EurocSequence(seq.mav0).root == seq.root


def test_euroc_sequence_tum_fallback_and_missing_parts(tmp_path):
    root = tmp_path / "MH_like"
    shutil.copytree(MAV0 / "imu0", root / "mav0" / "imu0")
    seq = EurocSequence(root)
    assert not seq.has_camera and not seq.has_groundtruth
    with pytest.raises(FileNotFoundError, match="no ground truth"):
        _ = seq.groundtruth
    with pytest.raises(FileNotFoundError):
        _ = seq.frame_t_ns
    gt = read_euroc_groundtruth(MAV0 / "state_groundtruth_estimate0" / "data.csv")
    write_tum(root / "groundtruth_tum.txt", gt)
    seq = EurocSequence(root)
    assert seq.has_groundtruth
    np.testing.assert_array_equal(seq.groundtruth.t_ns, gt.t_ns)
    assert seq.groundtruth.velocity is None
    with pytest.raises(FileNotFoundError, match="expected a 'mav0' folder"):
        EurocSequence(tmp_path / "nothing")


def test_writers_produce_a_readable_asl_folder(tmp_path):
    """A folder written only with the writers (as the simulator does) reads back through EurocSequence."""
    mav0 = tmp_path / "sim_seq" / "mav0"
    gt = read_euroc_groundtruth(MAV0 / "state_groundtruth_estimate0" / "data.csv")
    imu = read_euroc_imu(MAV0 / "imu0" / "data.csv")
    write_euroc_groundtruth(mav0 / "state_groundtruth_estimate0" / "data.csv", gt)
    write_euroc_imu(mav0 / "imu0" / "data.csv", imu)
    write_imu_yaml(mav0 / "imu0" / "sensor.yaml", ImuNoise())
    camera = CameraModel(8, 6, 5.0, 5.0, 3.5, 2.5)
    write_camera_yaml(mav0 / "cam0" / "sensor.yaml", CameraCalibration(camera, np.eye(4), 20.0))
    frame_t_ns = gt.t_ns[::10]
    paths = write_euroc_camera(mav0 / "cam0", frame_t_ns)
    for k, path in enumerate(paths):
        cv2.imwrite(str(path), np.full((6, 8), k, np.uint8))
    assert (mav0 / "cam0" / "data.csv").read_text().splitlines()[1] == f"{frame_t_ns[0]},{frame_t_ns[0]}.png"

    seq = EurocSequence(tmp_path / "sim_seq")
    np.testing.assert_array_equal(seq.frame_t_ns, frame_t_ns)
    assert seq.frame_paths == paths
    np.testing.assert_array_equal(seq.imu.acc, imu.acc)
    np.testing.assert_array_equal(seq.groundtruth.bias_gyro, gt.bias_gyro)
    assert seq.camera_calibration.camera == camera
    assert seq.imu_noise.acc_random_walk == ImuNoise().acc_random_walk
