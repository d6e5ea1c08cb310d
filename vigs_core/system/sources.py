"""Inputs of the in-process pipeline: an EuRoC ASL folder or a ROS 2 / ROS 1 bag, as one frame stream with the
camera calibration, the camera-IMU extrinsic and the ground truth when present."""
from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from vigs_core.camera import CameraModel
from vigs_core.types import BadFrame, ImuNoise, ImuSamples, Trajectory

GROUNDTRUTH_NAMES = ("groundtruth_tum.txt", "groundtruth.txt", "groundtruth.csv")


@dataclass
class InputSequence:
    """A camera stream.

    Attributes:
        name: sequence name.
        camera: calibrated (possibly distorted) camera of the images.
        T_BS: (4, 4) camera pose in the body (IMU) frame.
        frame_count: number of frames.
        frames: callable returning an iterator of ``(t_ns, grey image (H, W) uint8)`` in time order, with a
            :class:`~vigs_core.types.BadFrame` in place of an image that cannot be read or decoded.
        groundtruth: body trajectory in the world, or None.
        imu: IMU samples (body frame, same clock as the images), or None.
        imu_noise: the IMU's noise densities (EuRoC ADIS16448 defaults when the input has none).
    """

    name: str
    camera: CameraModel
    T_BS: np.ndarray
    frame_count: int
    frames: Callable[[], Iterator[tuple[int, np.ndarray]]]
    groundtruth: Trajectory | None
    imu: ImuSamples | None = None
    imu_noise: ImuNoise | None = None


class MissingImuWarning(UserWarning):
    """An input without IMU data: the run is vision-only (arbitrary scale)."""


def _grey(image: np.ndarray | BadFrame) -> np.ndarray | BadFrame:
    if isinstance(image, BadFrame):
        return image
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.dtype != np.uint8:
        return BadFrame(f"image of dtype {image.dtype}; expected 8-bit (mono8 / rgb8)")
    return image


def open_euroc(root: str | Path) -> InputSequence:
    """EuRoC ASL folder (``mav0/cam0`` with sensor.yaml; ground truth optional)."""
    from vigs_core.io import EurocSequence

    seq = EurocSequence(root)
    calib = seq.camera_calibration
    t_ns, paths = seq.frame_t_ns, seq.frame_paths

    def frames():
        for t, p in zip(t_ns, paths):
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            yield int(t), _grey(BadFrame(f"cannot read image {p}") if img is None else img)

    gt = seq.groundtruth if seq.has_groundtruth else None
    has_imu = (seq.imu_dir / "data.csv").is_file()
    if not has_imu:
        warnings.warn(f"{root}: no {seq.imu_dir / 'data.csv'}: vision only (no metric scale)", MissingImuWarning,
                      stacklevel=2)
    imu = seq.imu if has_imu else None
    noise = seq.imu_noise if has_imu and (seq.imu_dir / "sensor.yaml").is_file() else ImuNoise()
    return InputSequence(seq.name, calib.camera, np.asarray(calib.T_BS, dtype=np.float64), len(t_ns), frames, gt,
                         imu, noise)


def _groundtruth_beside(path: Path) -> Trajectory | None:
    from vigs_core.io import read_trajectory

    candidates = [path.parent / f"{path.stem}_groundtruth_tum.txt", path.parent / f"{path.name}_groundtruth_tum.txt"]
    candidates += [path / n for n in GROUNDTRUTH_NAMES] if path.is_dir() else []
    candidates += [path.parent / n for n in GROUNDTRUTH_NAMES]
    for c in candidates:
        if c.is_file():
            return read_trajectory(c)
    return None


def open_bag(path: str | Path, image_topic: str | None = None) -> InputSequence:
    """ROS 2 (MCAP / sqlite3 directory) or ROS 1 (.bag) recording with images and CameraInfo; the extrinsic
    from ``/tf_static`` (identity when absent); ground truth from the bag or a file beside it
    (``<bag>_groundtruth_tum.txt``, ``groundtruth_tum.txt``, ``groundtruth.txt``, ``groundtruth.csv``)."""
    from vigs_core.io.rosbag import read_bag

    path = Path(path)
    rec = read_bag(path, image_topic=image_topic)
    if rec.image_topic is None or rec.image_count == 0:
        raise ValueError(f"{path}: no camera images found (expected sensor_msgs/Image or CompressedImage)")
    if rec.camera is None:
        raise ValueError(f"{path}: no sensor_msgs/CameraInfo for {rec.image_topic}; the intrinsics are needed")
    gt = rec.groundtruth if rec.groundtruth is not None else _groundtruth_beside(path)

    def frames():
        for t, img in rec.images():
            yield int(t), _grey(img)

    T_BS = rec.T_BS if rec.T_BS is not None else np.eye(4)
    imu = rec.imu if len(rec.imu) else None
    return InputSequence(path.stem, rec.camera, np.asarray(T_BS, dtype=np.float64), rec.image_count, frames, gt,
                         imu, ImuNoise())


def open_input(path: str | Path, image_topic: str | None = None) -> InputSequence:
    """An EuRoC ASL folder (has ``mav0``, or is one) or a bag (ROS 2 directory with metadata.yaml / .mcap /
    .db3, or a ROS 1 .bag file)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist (expected an EuRoC ASL folder or a ROS bag)")
    if path.is_dir() and ((path / "mav0").is_dir() or path.name == "mav0"):
        return open_euroc(path)
    bag_dir = path.is_dir() and any((path / "metadata.yaml").is_file() or any(path.glob(f"*{ext}"))
                                    for ext in (".mcap", ".db3"))
    if bag_dir or path.suffix in (".bag", ".mcap", ".db3"):
        return open_bag(path, image_topic)
    raise ValueError(f"{path}: neither an EuRoC ASL folder (with mav0/) nor a ROS bag (a directory with "
                     "metadata.yaml or an .mcap / .db3 file, or a ROS 1 .bag)")
