"""Calibration files: EuRoC sensor.yaml, Kalibr camchain and imu.yaml."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from vigs_core.camera import CameraModel
from vigs_core.io import CameraCalibration, read_camera_yaml, read_imu_yaml, write_camera_yaml, write_imu_yaml
from vigs_core.types import ImuNoise

EXCERPT = Path(__file__).parent / "data" / "euroc_excerpt"
EUROC_T_BS = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def test_euroc_camera_sensor_yaml():
    cal = read_camera_yaml(EXCERPT / "mav0" / "cam0" / "sensor.yaml")
    cam = cal.camera
    assert (cam.width, cam.height) == (752, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (458.654, 457.296, 367.215, 248.375)
    assert cam.distortion == "radtan"
    assert cam.coeffs == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    np.testing.assert_array_equal(cal.T_BS, EUROC_T_BS)
    assert cal.rate_hz == 20.0 and cal.time_shift_s == 0.0


def test_euroc_imu_sensor_yaml():
    noise = read_imu_yaml(EXCERPT / "mav0" / "imu0" / "sensor.yaml")
    assert noise.gyro_noise_density == 1.6968e-04
    assert noise.gyro_random_walk == 1.9393e-05
    assert noise.acc_noise_density == 2.0e-3
    assert noise.acc_random_walk == 3.0e-3
    assert noise.rate_hz == 200.0
    np.testing.assert_array_equal(noise.T_BS, np.eye(4))


def kalibr_camchain(distortion_model: str, coeffs: list[float]) -> dict:
    return {
        "cam0": {
            "camera_model": "pinhole",
            "intrinsics": [190.97, 190.97, 254.93, 256.89],
            "distortion_model": distortion_model,
            "distortion_coeffs": coeffs,
            "resolution": [512, 512],
            "T_cam_imu": np.linalg.inv(EUROC_T_BS).tolist(),
            "timeshift_cam_imu": -8.1e-05,
            "rostopic": "/cam0/image_raw",
        }
    }


@pytest.mark.parametrize(
    "model, expected", [("equidistant", "equidistant"), ("radtan", "radtan"), ("none", "none")]
)
def test_kalibr_camchain(tmp_path, model, expected):
    coeffs = [0.0034, 0.0007, -0.0020, 0.0002] if model != "none" else []
    path = tmp_path / "camchain.yaml"
    path.write_text(yaml.safe_dump(kalibr_camchain(model, coeffs)))
    cal = read_camera_yaml(path)
    assert cal.camera.distortion == expected
    assert cal.camera.coeffs == tuple(coeffs)
    assert (cal.camera.width, cal.camera.fx, cal.camera.cy) == (512, 190.97, 256.89)
    np.testing.assert_allclose(cal.T_BS, EUROC_T_BS, atol=1e-12)
    assert cal.rate_hz is None
    assert cal.time_shift_s == -8.1e-05


def test_kalibr_camchain_selects_camera_and_reports_missing(tmp_path):
    chain = kalibr_camchain("radtan", [0.1, 0.01, 0.0, 0.0])
    chain["cam1"] = dict(chain["cam0"], intrinsics=[100.0, 100.0, 50.0, 50.0])
    path = tmp_path / "camchain.yaml"
    path.write_text(yaml.safe_dump(chain))
    assert read_camera_yaml(path, camera="cam1").camera.fx == 100.0
    with pytest.raises(ValueError, match=r"Kalibr camchain entry 'cam2' \(entries present: cam0, cam1\)"):
        read_camera_yaml(path, camera="cam2")


@pytest.mark.parametrize("nested", [True, False])
def test_kalibr_imu_yaml(tmp_path, nested):
    T_i_b = np.eye(4)
    T_i_b[:3, 3] = [0.1, -0.2, 0.3]
    entry = {
        "accelerometer_noise_density": 0.0028,
        "accelerometer_random_walk": 0.00086,
        "gyroscope_noise_density": 0.00016,
        "gyroscope_random_walk": 2.2e-05,
        "update_rate": 200.0,
        "rostopic": "/imu0",
        "T_i_b": T_i_b.tolist(),
    }
    path = tmp_path / "imu.yaml"
    path.write_text(yaml.safe_dump({"imu0": entry} if nested else entry))
    noise = read_imu_yaml(path)
    assert (noise.acc_noise_density, noise.acc_random_walk) == (0.0028, 0.00086)
    assert (noise.gyro_noise_density, noise.gyro_random_walk) == (0.00016, 2.2e-05)
    assert noise.rate_hz == 200.0
    np.testing.assert_allclose(noise.T_BS[:3, 3], [-0.1, 0.2, -0.3])


def test_opencv_matrix_tag_is_read(tmp_path):
    text = (EXCERPT / "mav0" / "cam0" / "sensor.yaml").read_text()
    text = text.replace("T_BS:\n", "T_BS: !!opencv-matrix\n")
    path = tmp_path / "sensor.yaml"
    path.write_text(text)
    np.testing.assert_array_equal(read_camera_yaml(path).T_BS, EUROC_T_BS)


@pytest.mark.parametrize(
    "edit, fragment",
    [
        (("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296, 367.215]"),
         "key 'intrinsics' must be a list of 4 numbers, found 3"),
        (("rate_hz: 20\n", ""), "missing key 'rate_hz'"),
        (("radial-tangential", "omnidirectional"), "distortion model 'omnidirectional' is not supported"),
        (("camera_model: pinhole", "camera_model: omni"), "camera_model 'omni' is not supported"),
        (("0.0148655429818, -0.999880929698", "1.0148655429818, -0.999880929698"), "'T_BS' is not a rigid transform"),
        (("resolution: [752, 480]", "resolution: [752, -480]"), "invalid camera calibration"),
        (("T_BS:", "T_SB:"), "missing key 'T_BS'"),
    ],
)
def test_camera_yaml_errors_name_the_key(tmp_path, edit, fragment):
    text = (EXCERPT / "mav0" / "cam0" / "sensor.yaml").read_text()
    assert edit[0] in text
    path = tmp_path / "sensor.yaml"
    path.write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(ValueError) as info:
        read_camera_yaml(path)
    assert str(path) in str(info.value)
    assert fragment in str(info.value)


def test_imu_yaml_errors(tmp_path):
    text = (EXCERPT / "mav0" / "imu0" / "sensor.yaml").read_text()
    path = tmp_path / "sensor.yaml"
    path.write_text(text.replace("gyroscope_random_walk", "gyro_rw"))
    with pytest.raises(ValueError, match="missing key 'gyroscope_random_walk'"):
        read_imu_yaml(path)
    path.write_text("imu0: [1, 2\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        read_imu_yaml(path)
    with pytest.raises(FileNotFoundError, match="no such calibration file"):
        read_imu_yaml(tmp_path / "missing.yaml")


@pytest.mark.parametrize(
    "distortion, coeffs",
    [("radtan", (-0.28, 0.07, 1e-4, -2e-5)), ("radtan", (-0.28, 0.07, 1e-4, -2e-5, 0.01)),
     ("equidistant", (0.01, -0.002, 3e-4, -1e-5)), ("none", ())],
)
def test_camera_yaml_write_read_round_trip(tmp_path, distortion, coeffs):
    T_BS = np.linalg.inv(EUROC_T_BS)
    cal = CameraCalibration(CameraModel(640, 400, 320.5, 321.25, 319.5, 199.5, distortion, coeffs), T_BS, 30.0)
    path = tmp_path / "cam0" / "sensor.yaml"
    write_camera_yaml(path, cal)
    assert path.read_text().startswith("%YAML:1.0\n")
    back = read_camera_yaml(path)
    assert back.camera == cal.camera
    np.testing.assert_array_equal(back.T_BS, T_BS)
    assert back.rate_hz == 30.0
    with pytest.raises(ValueError, match="needs rate_hz"):
        write_camera_yaml(path, CameraCalibration(cal.camera, T_BS, None))
    with pytest.raises(ValueError, match="no camera-IMU time shift"):
        write_camera_yaml(path, CameraCalibration(cal.camera, T_BS, 30.0, time_shift_s=0.001))


def test_imu_yaml_write_read_round_trip(tmp_path):
    T_BS = np.eye(4)
    T_BS[:3, 3] = [0.01, 0.02, -0.03]
    noise = ImuNoise(1.1e-4, 2.2e-5, 3.3e-3, 4.4e-4, 400.0, T_BS)
    path = tmp_path / "imu0" / "sensor.yaml"
    write_imu_yaml(path, noise)
    back = read_imu_yaml(path)
    assert (back.gyro_noise_density, back.gyro_random_walk) == (1.1e-4, 2.2e-5)
    assert (back.acc_noise_density, back.acc_random_walk, back.rate_hz) == (3.3e-3, 4.4e-4, 400.0)
    np.testing.assert_array_equal(back.T_BS, T_BS)
