"""EuRoC ASL CSV files (Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 2016).

Layouts (stamps in integer nanoseconds, ``#`` header line):

* ``imu0/data.csv``: ``timestamp, w_x, w_y, w_z [rad/s], a_x, a_y, a_z [m/s^2]`` (IMU frame S).
* ``state_groundtruth_estimate0/data.csv``: ``timestamp, p_x, p_y, p_z [m], q_w, q_x, q_y, q_z,
  v_x, v_y, v_z [m/s], bw_x, bw_y, bw_z [rad/s], ba_x, ba_y, ba_z [m/s^2]`` (17 columns): pose
  ``T_RS`` of the body (IMU) frame in the world R, world-frame velocity, gyro and accelerometer biases.
  Pose-only files with the first 8 columns (``vicon0/data.csv``, TUM-VI ``mocap0``) are read too.
* ``cam0/data.csv``: ``timestamp, filename``; images in ``cam0/data/<filename>``.

Readers return rows sorted by stamp and reject repeated stamps, except the ground-truth reader, which keeps
the first row of each with a warning (see :func:`stamp_order`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from vigs_core.io.text_table import (
    MalformedFileError,
    data_lines,
    normalized_quaternions,
    read_stamped_rows,
    split_fields,
    stamp_order,
)
from vigs_core.types import ImuSamples, Trajectory

IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GROUNDTRUTH_HEADER = (
    "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
POSE_HEADER = GROUNDTRUTH_HEADER.split(", v_RS_R_x")[0]
IMU_LAYOUT = "timestamp[ns], gyro x y z [rad/s], acc x y z [m/s^2]"
GROUNDTRUTH_LAYOUT = (
    "timestamp[ns], p x y z [m], q w x y z, then optionally v x y z [m/s], bias gyro x y z [rad/s], "
    "bias acc x y z [m/s^2]"
)


def read_euroc_imu(csv: str | Path, recorded_order: bool = False) -> ImuSamples:
    """Read an EuRoC ``imu0/data.csv`` into :class:`ImuSamples`, sorted by stamp (a repeated stamp is an error);
    with ``recorded_order`` the rows as the file has them (for checks that count disordered stamps). A sample with
    a non-finite value is left out with a warning, as the IMU node drops such a message: the stream then has a gap
    there, which the estimator handles as any other."""
    t_ns, values, lines = read_stamped_rows(csv, (7,), "comma", "ns", IMU_LAYOUT, skip_nonfinite=True)
    order = np.arange(len(t_ns)) if recorded_order else stamp_order(csv, t_ns, lines)
    return ImuSamples(t_ns[order], values[order, 0:3], values[order, 3:6])


def write_euroc_imu(csv: str | Path, imu: ImuSamples) -> None:
    """Write :class:`ImuSamples` as an EuRoC ``imu0/data.csv`` (exact stamps, shortest exact floats)."""
    rows = np.concatenate((imu.gyro, imu.acc), axis=1)
    _write_rows(csv, IMU_HEADER, imu.t_ns, rows)


def read_euroc_groundtruth(csv: str | Path) -> Trajectory:
    """Read an EuRoC ground-truth CSV (17 columns, or 8 pose-only columns) into a :class:`Trajectory`.

    With 17 columns the trajectory carries ``velocity``, ``bias_gyro`` and ``bias_acc``; with 8 they
    are ``None``. Quaternions are ``(w, x, y, z)`` in the file and in :class:`Trajectory`. A repeated stamp keeps
    its first row, with a warning.
    """
    t_ns, values, lines = read_stamped_rows(csv, (8, 17), "comma", "ns", GROUNDTRUTH_LAYOUT)
    quat = normalized_quaternions(csv, values[:, 3:7], lines)
    order = stamp_order(csv, t_ns, lines, keep_first=True)
    values, quat = values[order], quat[order]
    if values.shape[1] == 7:
        return Trajectory(t_ns[order], values[:, 0:3], quat)
    return Trajectory(
        t_ns[order],
        values[:, 0:3],
        quat,
        velocity=values[:, 7:10],
        bias_gyro=values[:, 10:13],
        bias_acc=values[:, 13:16],
    )


def write_euroc_groundtruth(csv: str | Path, trajectory: Trajectory) -> None:
    """Write a :class:`Trajectory` as an EuRoC ground-truth CSV.

    17 columns when velocity and both biases are present, the 8 pose columns when none is; a
    trajectory with only some of them is rejected (the file would not say which are missing).
    """
    extras = {"velocity": trajectory.velocity, "bias_gyro": trajectory.bias_gyro, "bias_acc": trajectory.bias_acc}
    present = [name for name, value in extras.items() if value is not None]
    if len(present) == 3:
        rows = np.concatenate((trajectory.position, trajectory.quat_wxyz, *extras.values()), axis=1)
        _write_rows(csv, GROUNDTRUTH_HEADER, trajectory.t_ns, rows)
    elif not present:
        rows = np.concatenate((trajectory.position, trajectory.quat_wxyz), axis=1)
        _write_rows(csv, POSE_HEADER, trajectory.t_ns, rows)
    else:
        missing = [name for name in extras if name not in present]
        raise ValueError(
            f"write_euroc_groundtruth: trajectory has {', '.join(present)} but not {', '.join(missing)}; "
            "expected all of velocity, bias_gyro, bias_acc (17 columns) or none (8 pose columns)"
        )


def read_euroc_camera(cam_dir: str | Path, check_images: bool = True) -> tuple[np.ndarray, list[Path]]:
    """Read an EuRoC camera folder (``cam0/data.csv`` + ``cam0/data/*.png``).

    Args:
        cam_dir: the camera folder, e.g. ``.../mav0/cam0``.
        check_images: raise if an image named in ``data.csv`` does not exist.

    Returns:
        ``t_ns`` (N,) int64 frame stamps (sorted) and the N image paths.

    Raises:
        FileNotFoundError: ``data.csv`` missing, or (with ``check_images``) images missing; the message
            gives how many and the first few names.
        MalformedFileError: a line that is not ``timestamp[ns],filename``.
    """
    cam_dir = Path(cam_dir)
    csv = cam_dir / "data.csv"
    stamps, names, lines = [], [], []
    for number, text in data_lines(csv):
        fields = split_fields(text, "comma")
        if len(fields) != 2 or not fields[1]:
            raise MalformedFileError(csv, number, f"expected 'timestamp[ns],filename', found '{text[:80]}'")
        try:
            stamps.append(int(fields[0]))
        except ValueError:
            raise MalformedFileError(
                csv, number, f"column 1 (time stamp) must be integer nanoseconds, found '{fields[0]}'"
            ) from None
        names.append(fields[1])
        lines.append(number)
    if not stamps:
        raise MalformedFileError(csv, 0, "no data rows; expected lines of 'timestamp[ns],filename'")
    t_ns = np.array(stamps, dtype=np.int64)
    order = stamp_order(csv, t_ns, np.array(lines))
    paths = [cam_dir / "data" / names[i] for i in order]
    if check_images:
        missing = [p.name for p in paths if not p.is_file()]
        if missing:
            shown = ", ".join(missing[:5]) + (", ..." if len(missing) > 5 else "")
            raise FileNotFoundError(
                f"{cam_dir / 'data'}: {len(missing)} of {len(paths)} images listed in {csv} are missing ({shown})"
            )
    return t_ns[order], paths


def write_euroc_camera(cam_dir: str | Path, t_ns: np.ndarray, extension: str = "png") -> list[Path]:
    """Write ``cam_dir/data.csv`` for frames stamped ``t_ns`` (N,) and create ``cam_dir/data/``.

    Images are named ``<stamp>.<extension>`` as in EuRoC; the caller writes them to the returned N paths
    (e.g. ``cv2.imwrite``).
    """
    cam_dir = Path(cam_dir)
    (cam_dir / "data").mkdir(parents=True, exist_ok=True)
    names = [f"{int(t)}.{extension}" for t in np.asarray(t_ns, dtype=np.int64)]
    with (cam_dir / "data.csv").open("w", encoding="utf-8") as f:
        f.write("#timestamp [ns],filename\n")
        for t, name in zip(np.asarray(t_ns, dtype=np.int64), names):
            f.write(f"{int(t)},{name}\n")
    return [cam_dir / "data" / name for name in names]


def _write_rows(csv: str | Path, header: str, t_ns: np.ndarray, rows: np.ndarray) -> None:
    csv = Path(csv)
    csv.parent.mkdir(parents=True, exist_ok=True)
    with csv.open("w", encoding="utf-8") as f:
        f.write(header + "\n")
        for t, row in zip(t_ns, rows):
            f.write(f"{int(t)}," + ",".join(repr(float(v)) for v in row) + "\n")
