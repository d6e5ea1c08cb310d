"""Dataset and calibration files: EuRoC ASL folders, TUM trajectories, EuRoC / Kalibr calibration YAML.

Conventions: stamps are integer nanoseconds kept exact (no float round trip); quaternions are Hamilton
``(w, x, y, z)`` in memory (EuRoC order) and ``(x, y, z, w)`` in TUM text; extrinsics are ``T_BS``
(sensor pose in the body/IMU frame). Malformed files raise :class:`MalformedFileError` (a ``ValueError``)
naming the file, the line and what was expected.
"""
from vigs_core.io.calibration import (
    CameraCalibration,
    load_calibration_yaml,
    read_camera_yaml,
    read_imu_yaml,
    write_camera_yaml,
    write_imu_yaml,
)
from vigs_core.io.euroc import (
    read_euroc_camera,
    read_euroc_groundtruth,
    read_euroc_imu,
    write_euroc_camera,
    write_euroc_groundtruth,
    write_euroc_imu,
)
from vigs_core.io.euroc_sequence import EurocSequence
from vigs_core.io.frame_schedule import read_frame_schedule, write_frame_schedule
from vigs_core.io.frame_status import read_frame_status, write_frame_status
from vigs_core.io.text_table import MalformedFileError, ns_to_seconds_text, seconds_to_ns
from vigs_core.io.trajectory_file import read_trajectory, trajectory_format
from vigs_core.io.tum import read_tum, write_tum

__all__ = [
    "CameraCalibration",
    "EurocSequence",
    "MalformedFileError",
    "load_calibration_yaml",
    "ns_to_seconds_text",
    "read_camera_yaml",
    "read_euroc_camera",
    "read_euroc_groundtruth",
    "read_euroc_imu",
    "read_frame_schedule",
    "read_frame_status",
    "read_imu_yaml",
    "read_trajectory",
    "read_tum",
    "seconds_to_ns",
    "trajectory_format",
    "write_camera_yaml",
    "write_euroc_camera",
    "write_euroc_groundtruth",
    "write_euroc_imu",
    "write_frame_schedule",
    "write_frame_status",
    "write_imu_yaml",
    "write_tum",
]
