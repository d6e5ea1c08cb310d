"""Camera and IMU calibration files: EuRoC ``sensor.yaml`` and Kalibr camchain / IMU YAML.

Extrinsics are returned as ``T_BS`` (4, 4): the pose of the sensor frame S in the body frame B, i.e.
``p_B = T_BS p_S`` (EuRoC's convention; the body frame is the IMU frame in EuRoC). Kalibr stores the
opposite direction, ``T_cam_imu`` (maps IMU-frame points into the camera frame) and ``T_i_b`` (maps body
points into the IMU frame), so ``T_BS = inverse(T_cam_imu)`` and ``T_BS = inverse(T_i_b)``.

File layouts read (keys as written by the tools):

* EuRoC camera ``sensor.yaml``: ``T_BS {rows, cols, data (row-major)}``, ``rate_hz``, ``resolution
  [w, h]``, ``camera_model: pinhole``, ``intrinsics [fu, fv, cu, cv]``, ``distortion_model:
  radial-tangential | equidistant``, ``distortion_coefficients``.
* EuRoC IMU ``sensor.yaml``: ``T_BS``, ``rate_hz``, ``gyroscope_noise_density``,
  ``gyroscope_random_walk``, ``accelerometer_noise_density``, ``accelerometer_random_walk``.
* Kalibr camchain: ``cam0: {camera_model: pinhole, intrinsics, distortion_model: radtan | equidistant,
  distortion_coeffs, resolution, T_cam_imu (4x4 nested list), timeshift_cam_imu}``.
* Kalibr IMU: ``imu0: {accelerometer_noise_density, accelerometer_random_walk, gyroscope_noise_density,
  gyroscope_random_walk, update_rate, T_i_b}`` (or the same keys at the top level, older Kalibr).

EuRoC files start with OpenCV's ``%YAML:1.0`` line, which is not valid YAML 1.1; it is dropped before
parsing, and OpenCV's ``!!opencv-matrix`` tag is read as a plain mapping. The writers produce EuRoC
``sensor.yaml`` files (so simulated ASL folders read like real ones).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from vigs_core.types import ImuNoise

if TYPE_CHECKING:
    from vigs_core.camera import CameraModel

# CameraModel distortion names -> EuRoC sensor.yaml spelling (written by write_camera_yaml).
_EUROC_DISTORTION_NAMES = {"none": "none", "radtan": "radial-tangential", "equidistant": "equidistant"}
# Spellings of distortion models in EuRoC, Kalibr and ROS camera_info files -> CameraModel names.
_DISTORTION_NAMES = {
    "none": "none",
    "radial-tangential": "radtan",
    "radtan": "radtan",
    "plumb_bob": "radtan",
    "equidistant": "equidistant",
    "equidist": "equidistant",
    "equi": "equidistant",
    "fisheye": "equidistant",
}


@dataclass
class CameraCalibration:
    """Intrinsics, extrinsics and timing of one camera.

    Attributes:
        camera: the camera model (intrinsics and distortion).
        T_BS: (4, 4) float64 pose of the camera in the body (IMU) frame, ``p_B = T_BS p_C``.
        rate_hz: nominal frame rate (Hz); ``None`` when the file does not say (Kalibr camchain).
        time_shift_s: camera-to-IMU clock offset, ``t_imu = t_cam + time_shift_s`` (Kalibr
            ``timeshift_cam_imu``; 0 for EuRoC, whose streams share one clock).
    """

    camera: CameraModel
    T_BS: np.ndarray
    rate_hz: float | None
    time_shift_s: float = 0.0


class _CalibrationLoader(yaml.SafeLoader):
    """SafeLoader that reads OpenCV's ``!!opencv-matrix`` nodes as mappings."""


_CalibrationLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix", lambda loader, node: loader.construct_mapping(node, deep=True)
)


def load_calibration_yaml(path: str | Path) -> dict:
    """Parse a calibration YAML file (EuRoC/OpenCV or Kalibr) into a dict."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such calibration file")
    text = path.read_text(encoding="utf-8")
    if text.startswith("%YAML:"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        content = yaml.load(text, Loader=_CalibrationLoader)
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(content, dict):
        raise ValueError(f"{path}: expected a YAML mapping of calibration keys, found {type(content).__name__}")
    return content


def read_camera_yaml(path: str | Path, camera: str = "cam0") -> CameraCalibration:
    """Read a camera calibration: EuRoC ``sensor.yaml`` or Kalibr camchain (entry ``camera``).

    Raises:
        ValueError: a missing or malformed key, an unsupported camera or distortion model; the
            message names the file and the key.
    """
    content = load_calibration_yaml(path)
    if "intrinsics" in content:
        return _euroc_camera(path, content)
    if camera in content and isinstance(content[camera], dict):
        return _kalibr_camera(path, camera, content[camera])
    cams = [key for key, value in content.items() if isinstance(value, dict) and "intrinsics" in value]
    raise ValueError(
        f"{path}: no camera calibration found; expected EuRoC sensor.yaml keys (intrinsics, T_BS, ...) or a "
        f"Kalibr camchain entry '{camera}'" + (f" (entries present: {', '.join(cams)})" if cams else "")
    )


def read_imu_yaml(path: str | Path) -> ImuNoise:
    """Read IMU noise parameters: EuRoC ``sensor.yaml`` or Kalibr ``imu.yaml`` (``imu0`` entry or top level).

    ``T_BS`` comes from EuRoC's ``T_BS`` or Kalibr's ``T_i_b`` (inverted); it is the identity when the
    file has neither (single-IMU Kalibr files, where the IMU is the body frame).

    Raises:
        ValueError: a missing noise key or malformed transform (the message names file and key).
    """
    content = load_calibration_yaml(path)
    if "gyroscope_noise_density" not in content and isinstance(content.get("imu0"), dict):
        content = content["imu0"]
    if "T_BS" in content:
        T_BS = _euroc_matrix(path, content, "T_BS")
    elif "T_i_b" in content:
        T_BS = np.linalg.inv(_nested_matrix(path, content, "T_i_b"))
    else:
        T_BS = np.eye(4)
    rate_key = "rate_hz" if "rate_hz" in content else "update_rate"
    return ImuNoise(
        gyro_noise_density=_number(path, content, "gyroscope_noise_density"),
        gyro_random_walk=_number(path, content, "gyroscope_random_walk"),
        acc_noise_density=_number(path, content, "accelerometer_noise_density"),
        acc_random_walk=_number(path, content, "accelerometer_random_walk"),
        rate_hz=_number(path, content, rate_key),
        T_BS=T_BS,
    )


def write_camera_yaml(path: str | Path, calibration: CameraCalibration) -> None:
    """Write a camera calibration as a EuRoC ``sensor.yaml`` (read back by :func:`read_camera_yaml`).

    Raises:
        ValueError: no ``rate_hz``, or a non-zero ``time_shift_s`` (the EuRoC format has no key for it).
    """
    if calibration.rate_hz is None:
        raise ValueError(f"write_camera_yaml: {path}: a EuRoC sensor.yaml needs rate_hz; the calibration has None")
    if calibration.time_shift_s != 0.0:
        raise ValueError(
            f"write_camera_yaml: {path}: EuRoC sensor.yaml has no camera-IMU time shift; "
            f"got time_shift_s={calibration.time_shift_s}, expected 0"
        )
    cam = calibration.camera
    lines = [
        "sensor_type: camera",
        "comment: written by vigs_core.io",
        *_euroc_matrix_lines("T_BS", calibration.T_BS),
        f"rate_hz: {_number_text(calibration.rate_hz)}",
        f"resolution: [{cam.width}, {cam.height}]",
        "camera_model: pinhole",
        f"intrinsics: {_list_text((cam.fx, cam.fy, cam.cx, cam.cy))} # fu, fv, cu, cv",
        f"distortion_model: {_EUROC_DISTORTION_NAMES[cam.distortion]}",
        f"distortion_coefficients: {_list_text(cam.coeffs)}",
    ]
    _write_euroc_yaml(path, lines)


def write_imu_yaml(path: str | Path, noise: ImuNoise) -> None:
    """Write IMU noise parameters as a EuRoC ``sensor.yaml`` (read back by :func:`read_imu_yaml`)."""
    lines = [
        "sensor_type: imu",
        "comment: written by vigs_core.io",
        *_euroc_matrix_lines("T_BS", noise.T_BS),
        f"rate_hz: {_number_text(noise.rate_hz)}",
        f"gyroscope_noise_density: {_number_text(noise.gyro_noise_density)} # [ rad / s / sqrt(Hz) ]",
        f"gyroscope_random_walk: {_number_text(noise.gyro_random_walk)} # [ rad / s^2 / sqrt(Hz) ]",
        f"accelerometer_noise_density: {_number_text(noise.acc_noise_density)} # [ m / s^2 / sqrt(Hz) ]",
        f"accelerometer_random_walk: {_number_text(noise.acc_random_walk)} # [ m / s^3 / sqrt(Hz) ]",
    ]
    _write_euroc_yaml(path, lines)


def _write_euroc_yaml(path: str | Path, lines: list[str]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("%YAML:1.0\n" + "\n".join(lines) + "\n", encoding="utf-8")


def _euroc_matrix_lines(key: str, matrix: np.ndarray) -> list[str]:
    """EuRoC's ``{cols, rows, data}`` layout of a (4, 4) matrix, data row-major, one matrix row per line."""
    rows = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    data = ",\n         ".join(", ".join(_number_text(v) for v in row) for row in rows)
    return [f"{key}:", "  cols: 4", "  rows: 4", f"  data: [{data}]"]


def _number_text(value: float) -> str:
    """Shortest text that reads back as the same float (``repr``)."""
    return repr(float(value))


def _list_text(values) -> str:
    return "[" + ", ".join(_number_text(v) for v in values) + "]"


def _euroc_camera(path: str | Path, content: dict) -> CameraCalibration:
    model = _camera_model(
        path,
        content.get("camera_model", "pinhole"),
        _numbers(path, content, "resolution", 2),
        _numbers(path, content, "intrinsics", 4),
        content.get("distortion_model", "none"),
        _numbers(path, content, "distortion_coefficients") if "distortion_coefficients" in content else (),
    )
    return CameraCalibration(model, _euroc_matrix(path, content, "T_BS"), _number(path, content, "rate_hz"))


def _kalibr_camera(path: str | Path, name: str, entry: dict) -> CameraCalibration:
    where = f"{name}."
    model = _camera_model(
        path,
        entry.get("camera_model", "pinhole"),
        _numbers(path, entry, "resolution", 2, where),
        _numbers(path, entry, "intrinsics", 4, where),
        entry.get("distortion_model", "none"),
        _numbers(path, entry, "distortion_coeffs", None, where) if "distortion_coeffs" in entry else (),
    )
    T_cam_imu = _nested_matrix(path, entry, "T_cam_imu", where)
    shift = _number(path, entry, "timeshift_cam_imu", where) if "timeshift_cam_imu" in entry else 0.0
    return CameraCalibration(model, np.linalg.inv(T_cam_imu), None, shift)


def _camera_model(path, camera_model, resolution, intrinsics, distortion_model, coeffs) -> CameraModel:
    # Imported here: the camera package loads torch, which reading trajectories (``vigs eval``) never needs.
    from vigs_core.camera import CameraModel

    if camera_model != "pinhole":
        raise ValueError(f"{path}: camera_model '{camera_model}' is not supported; expected 'pinhole'")
    distortion = _DISTORTION_NAMES.get(str(distortion_model).lower())
    if distortion is None:
        raise ValueError(
            f"{path}: distortion model '{distortion_model}' is not supported; expected one of "
            + ", ".join(sorted(_DISTORTION_NAMES))
        )
    width, height = (int(round(v)) for v in resolution)
    fx, fy, cx, cy = intrinsics
    try:
        return CameraModel(width, height, fx, fy, cx, cy, distortion=distortion, coeffs=tuple(coeffs))
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: invalid camera calibration: {error}") from None


def _number(path, content: dict, key: str, where: str = "") -> float:
    if key not in content:
        raise ValueError(f"{path}: missing key '{where}{key}' (a number)")
    try:
        return float(content[key])
    except (TypeError, ValueError):
        raise ValueError(f"{path}: key '{where}{key}' must be a number, found {content[key]!r}") from None


def _numbers(path, content: dict, key: str, count: int | None = None, where: str = "") -> tuple[float, ...]:
    value = content.get(key)
    expected = f"a list of {count} numbers" if count else "a list of numbers"
    if value is None:
        raise ValueError(f"{path}: missing key '{where}{key}' ({expected})")
    try:
        numbers = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: key '{where}{key}' must be {expected}, found {value!r}") from None
    if count is not None and len(numbers) != count:
        raise ValueError(f"{path}: key '{where}{key}' must be {expected}, found {len(numbers)}")
    return numbers


def _euroc_matrix(path, content: dict, key: str) -> np.ndarray:
    """``{rows: 4, cols: 4, data: [16 numbers, row-major]}`` -> (4, 4)."""
    node = content.get(key)
    if node is None:
        raise ValueError(f"{path}: missing key '{key}' (4x4 matrix: rows, cols, data row-major)")
    if not isinstance(node, dict) or "data" not in node:
        raise ValueError(f"{path}: key '{key}' must be a mapping with rows, cols and data (row-major), found {node!r}")
    data = _numbers(path, node, "data", 16, f"{key}.")
    if int(node.get("rows", 4)) != 4 or int(node.get("cols", 4)) != 4:
        raise ValueError(f"{path}: key '{key}' must be 4x4, found {node.get('rows')}x{node.get('cols')}")
    return _checked_rigid(path, key, np.array(data, dtype=np.float64).reshape(4, 4))


def _nested_matrix(path, content: dict, key: str, where: str = "") -> np.ndarray:
    """Kalibr's 4x4 nested list ``[[r00, r01, r02, t0], ..., [0, 0, 0, 1]]`` -> (4, 4)."""
    value = content.get(key)
    if value is None:
        raise ValueError(f"{path}: missing key '{where}{key}' (4x4 nested list)")
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        matrix = None
    if matrix is None or matrix.shape != (4, 4):
        raise ValueError(f"{path}: key '{where}{key}' must be a 4x4 nested list of numbers, found {value!r}")
    return _checked_rigid(path, where + key, matrix)


def _checked_rigid(path, key: str, matrix: np.ndarray) -> np.ndarray:
    """Reject a transform whose rotation block is not orthonormal to 1e-4 or whose last row is not 0 0 0 1."""
    rot = matrix[:3, :3]
    if (
        np.abs(rot @ rot.T - np.eye(3)).max() > 1e-4
        or np.linalg.det(rot) < 0
        or np.abs(matrix[3] - (0, 0, 0, 1)).max() > 1e-9
    ):
        raise ValueError(
            f"{path}: key '{key}' is not a rigid transform; expected an orthonormal rotation block and last row 0 0 0 1"
        )
    return matrix
