"""One EuRoC ASL sequence folder: camera frames, IMU, ground truth and calibration in one object.

Layout (``root`` is the sequence folder holding ``mav0/``, or ``mav0/`` itself)::

    root/mav0/cam0/{data.csv, data/*.png, sensor.yaml}
    root/mav0/imu0/{data.csv, sensor.yaml}
    root/mav0/state_groundtruth_estimate0/data.csv      (preferred ground truth: pose, velocity, biases)
    root/groundtruth_tum.txt                            (fallback ground truth: TUM text, poses only)

Parts are read on first access and cached. A part that is absent raises ``FileNotFoundError`` naming
the files that were looked for; ``has_camera``, ``has_groundtruth`` say in advance.
"""
from __future__ import annotations

from functools import cached_property
from pathlib import Path

import numpy as np

from vigs_core.io.calibration import CameraCalibration, read_camera_yaml, read_imu_yaml
from vigs_core.io.euroc import read_euroc_camera, read_euroc_groundtruth, read_euroc_imu
from vigs_core.io.tum import read_tum
from vigs_core.types import ImuNoise, ImuSamples, Trajectory


class EurocSequence:
    """Lazy reader of one EuRoC ASL sequence.

    Args:
        root: the sequence folder (containing ``mav0``) or the ``mav0`` folder.
        camera: camera folder name under ``mav0`` (``"cam0"``).

    Attributes (each read on first access):
        frame_t_ns: (N,) int64 camera frame stamps (ns); ``frame_paths``: their N image paths.
        imu: :class:`ImuSamples` of ``imu0``.
        groundtruth: :class:`Trajectory` of the body (IMU) frame in the world, with velocity and
            biases when read from ``state_groundtruth_estimate0/data.csv``.
        camera_calibration: :class:`CameraCalibration` of ``cam0`` (intrinsics, T_BS, rate).
        imu_noise: :class:`ImuNoise` of ``imu0`` (noise densities, random walks, rate, T_BS).
    """

    def __init__(self, root: str | Path, camera: str = "cam0") -> None:
        root = Path(root)
        self.mav0 = root if root.name == "mav0" else root / "mav0"
        if not self.mav0.is_dir():
            raise FileNotFoundError(f"{root}: not a EuRoC ASL sequence (expected a 'mav0' folder at {self.mav0})")
        self.root = self.mav0.parent
        self.camera_dir = self.mav0 / camera
        self.imu_dir = self.mav0 / "imu0"
        self.groundtruth_csv = self.mav0 / "state_groundtruth_estimate0" / "data.csv"
        self.groundtruth_tum = self.root / "groundtruth_tum.txt"

    def __repr__(self) -> str:
        return f"EurocSequence('{self.root}')"

    @property
    def name(self) -> str:
        """The sequence folder's name, e.g. ``V1_01_easy``."""
        return self.root.name

    @property
    def has_camera(self) -> bool:
        return (self.camera_dir / "data.csv").is_file()

    @property
    def has_groundtruth(self) -> bool:
        return self.groundtruth_csv.is_file() or self.groundtruth_tum.is_file()

    @cached_property
    def _frames(self) -> tuple[np.ndarray, list[Path]]:
        return read_euroc_camera(self.camera_dir)

    @property
    def frame_t_ns(self) -> np.ndarray:
        return self._frames[0]

    @property
    def frame_paths(self) -> list[Path]:
        return self._frames[1]

    @cached_property
    def imu(self) -> ImuSamples:
        return read_euroc_imu(self.imu_dir / "data.csv")

    @cached_property
    def groundtruth(self) -> Trajectory:
        if self.groundtruth_csv.is_file():
            return read_euroc_groundtruth(self.groundtruth_csv)
        if self.groundtruth_tum.is_file():
            return read_tum(self.groundtruth_tum)
        raise FileNotFoundError(
            f"{self.root}: no ground truth (looked for {self.groundtruth_csv} and {self.groundtruth_tum})"
        )

    @cached_property
    def camera_calibration(self) -> CameraCalibration:
        return read_camera_yaml(self.camera_dir / "sensor.yaml")

    @cached_property
    def imu_noise(self) -> ImuNoise:
        return read_imu_yaml(self.imu_dir / "sensor.yaml")
