"""Writers of simulated sequences: EuRoC ASL folders (readable by :class:`vigs_core.io.EurocSequence`)
and ROS 2 bags (:class:`vigs_core.io.rosbag.BagWriter`), plus TUM ground truth.

ASL layout written by :class:`AslWriter`::

    root/mav0/cam0/{data.csv, data/<t_ns>.png, sensor.yaml}
    root/mav0/depth0/{data.csv, data/<t_ns>.tiff}          (float32 depth Z in metres, deflate TIFF, optional)
    root/mav0/imu0/{data.csv, sensor.yaml}
    root/mav0/state_groundtruth_estimate0/data.csv
    root/groundtruth_tum.txt                               (body frame, TUM text)
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vigs_core.camera import CameraModel
from vigs_core.io import write_euroc_groundtruth, write_euroc_imu, write_tum
from vigs_core.types import ImuNoise, ImuSamples, Trajectory

_TIFF_DEFLATE = 8  # libtiff COMPRESSION_ADOBE_DEFLATE
_EUROC_DISTORTION = {"none": "none", "radtan": "radial-tangential", "equidistant": "equidistant"}


def _matrix_yaml(T: np.ndarray) -> str:
    rows = [", ".join(repr(float(v)) for v in row) for row in np.asarray(T, dtype=np.float64)]
    return "  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def camera_sensor_yaml(camera: CameraModel, T_BS: np.ndarray, rate_hz: float) -> str:
    """EuRoC ``cam0/sensor.yaml`` text for a camera model and extrinsic."""
    coeffs = ", ".join(repr(float(c)) for c in camera.coeffs)
    return (
        "%YAML:1.0\n"
        "sensor_type: camera\n"
        "comment: rendered by vigs sim\n"
        "T_BS:\n" + _matrix_yaml(T_BS) + f"rate_hz: {rate_hz!r}\n"
        f"resolution: [{camera.width}, {camera.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{camera.fx!r}, {camera.fy!r}, {camera.cx!r}, {camera.cy!r}]\n"
        f"distortion_model: {_EUROC_DISTORTION[camera.distortion]}\n"
        f"distortion_coefficients: [{coeffs}]\n"
    )


def imu_sensor_yaml(noise: ImuNoise) -> str:
    """EuRoC ``imu0/sensor.yaml`` text for a noise model."""
    return (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        "comment: vigs sim\n"
        "T_BS:\n" + _matrix_yaml(noise.T_BS) + f"rate_hz: {noise.rate_hz!r}\n"
        f"gyroscope_noise_density: {noise.gyro_noise_density!r}\n"
        f"gyroscope_random_walk: {noise.gyro_random_walk!r}\n"
        f"accelerometer_noise_density: {noise.acc_noise_density!r}\n"
        f"accelerometer_random_walk: {noise.acc_random_walk!r}\n"
    )


class AslWriter:
    """Streams frames into an EuRoC ASL folder; IMU, ground truth and calibration are written by :meth:`close`.

    Args:
        root: output folder (created; must not contain a ``mav0`` folder already).
        camera: camera model (cam0/sensor.yaml).
        T_BS: (4, 4) camera pose in the body frame.
        rate_hz: nominal frame rate (Hz).
        with_depth: write ``depth0``.
    """

    def __init__(
        self, root: str | Path, camera: CameraModel, T_BS: np.ndarray, rate_hz: float, with_depth: bool
    ) -> None:
        self.root = Path(root)
        self.mav0 = self.root / "mav0"
        if self.mav0.exists():
            raise FileExistsError(f"AslWriter: {self.mav0} exists already; choose an empty output folder")
        (self.mav0 / "cam0" / "data").mkdir(parents=True)
        (self.mav0 / "cam0" / "sensor.yaml").write_text(camera_sensor_yaml(camera, T_BS, rate_hz))
        self.with_depth = with_depth
        if with_depth:
            (self.mav0 / "depth0" / "data").mkdir(parents=True)
        self.stamps: list[int] = []

    def write_frame(self, t_ns: int, image: np.ndarray, depth: np.ndarray | None = None) -> None:
        """One frame: (H, W) uint8 grey or (H, W, 3) uint8 RGB, and (H, W) float32 depth (m)."""
        name = f"{int(t_ns)}"
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
        if not cv2.imwrite(str(self.mav0 / "cam0" / "data" / f"{name}.png"), bgr):
            raise OSError(f"AslWriter: could not write {self.mav0 / 'cam0' / 'data' / name}.png")
        if self.with_depth and depth is not None:
            # deflate-compressed float32 TIFF: lossless, about half the raw size
            path = str(self.mav0 / "depth0" / "data" / f"{name}.tiff")
            cv2.imwrite(path, depth.astype(np.float32), [cv2.IMWRITE_TIFF_COMPRESSION, _TIFF_DEFLATE])
        self.stamps.append(int(t_ns))

    def close(self, imu: ImuSamples, imu_noise: ImuNoise, groundtruth: Trajectory) -> None:
        """Write the frame lists, IMU, IMU calibration and ground truth (EuRoC CSV and TUM text)."""
        lines = "".join(f"{t},{t}.png\n" for t in self.stamps)
        (self.mav0 / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n" + lines)
        if self.with_depth:
            depth_lines = "".join(f"{t},{t}.tiff\n" for t in self.stamps)
            (self.mav0 / "depth0" / "data.csv").write_text("#timestamp [ns],filename\n" + depth_lines)
        (self.mav0 / "imu0").mkdir(exist_ok=True)
        write_euroc_imu(self.mav0 / "imu0" / "data.csv", imu)
        (self.mav0 / "imu0" / "sensor.yaml").write_text(imu_sensor_yaml(imu_noise))
        (self.mav0 / "state_groundtruth_estimate0").mkdir(exist_ok=True)
        write_euroc_groundtruth(self.mav0 / "state_groundtruth_estimate0" / "data.csv", groundtruth)
        write_tum(self.root / "groundtruth_tum.txt", groundtruth)


def read_depth(path: str | Path) -> np.ndarray:
    """(H, W) float32 depth (m) from a ``depth0/data/*.tiff`` file written by :class:`AslWriter`."""
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if depth is None or depth.dtype != np.float32:
        raise ValueError(f"read_depth: {path} is not a float32 TIFF depth image")
    return depth
