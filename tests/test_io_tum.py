"""TUM trajectory text: exact stamps, round trips, format detection and malformed-file errors."""
from pathlib import Path

import numpy as np
import pytest

from vigs_core.io import (
    MalformedFileError,
    ns_to_seconds_text,
    read_trajectory,
    read_tum,
    seconds_to_ns,
    trajectory_format,
    write_tum,
)
from vigs_core.types import Trajectory

EXCERPT = Path(__file__).parent / "data" / "euroc_excerpt"


def random_trajectory(n: int, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    t_ns = 1403715273262142976 + np.cumsum(rng.integers(1, 10**8, size=n))
    return Trajectory(t_ns, rng.normal(size=(n, 3)) * 10, quat)


def test_seconds_to_ns_is_exact():
    assert seconds_to_ns("1403715274.30214") == 1403715274302140000
    assert seconds_to_ns("1403715273.262142976") == 1403715273262142976
    assert seconds_to_ns("1.5e-3") == 1_500_000
    assert seconds_to_ns("-0.000000001") == -1
    assert seconds_to_ns("0.0000000015") == 2  # half-to-even below 1 ns
    assert ns_to_seconds_text(1403715273262142976) == "1403715273.262142976"
    assert ns_to_seconds_text(-1) == "-0.000000001"
    with pytest.raises(ValueError):
        seconds_to_ns("12:30")
    with pytest.raises(ValueError):
        seconds_to_ns("inf")


def test_round_trip_keeps_nanoseconds_and_values(tmp_path):
    traj = random_trajectory(50)
    path = tmp_path / "sub" / "traj.txt"
    write_tum(path, traj)
    back = read_tum(path)
    np.testing.assert_array_equal(back.t_ns, traj.t_ns)
    np.testing.assert_allclose(back.position, traj.position, rtol=0, atol=1e-15)
    np.testing.assert_allclose(back.quat_wxyz, traj.quat_wxyz, rtol=0, atol=1e-15)
    assert back.velocity is None
    assert path.read_text().splitlines()[0].startswith("#")


def test_reads_real_excerpt_in_xyzw_order():
    # First row: "1403715284.30214 1.973584 2.542086 0.999385 0.631517 -0.536682 0.462396 0.315196"
    traj = read_tum(EXCERPT / "groundtruth_tum.txt")
    assert len(traj) == 40
    assert traj.t_ns[0] == 1403715284302140000
    np.testing.assert_allclose(traj.position[0], [1.973584, 2.542086, 0.999385])
    q = np.array([0.315196, 0.631517, -0.536682, 0.462396])
    np.testing.assert_allclose(traj.quat_wxyz[0], q / np.linalg.norm(q))
    assert np.all(np.diff(traj.t_ns) > 0)


def test_comments_commas_blank_lines_and_unsorted_rows(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text(
        "# timestamp tx ty tz qx qy qz qw\n\n"
        "2.5, 1, 2, 3, 0, 0, 0, 1\n"
        "# a comment in the middle\n"
        "1.25\t4 5 6   0 0 1 0\n"
    )
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.t_ns, [1_250_000_000, 2_500_000_000])
    np.testing.assert_allclose(traj.position, [[4, 5, 6], [1, 2, 3]])
    np.testing.assert_allclose(traj.quat_wxyz, [[0, 0, 0, 1], [1, 0, 0, 0]])


@pytest.mark.parametrize(
    "body, line, fragment",
    [
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", 3, "expected 8 columns"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n", 3, "column 4 must be a finite number"),
        ("1.0 0 0 0 0 0 0 1\nabc 0 0 0 0 0 0 1\n", 3, "column 1 (time stamp) must be decimal seconds"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n", 3, "column 4 must be a finite number"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 1 1 1 1\n", 3, "quaternion norm 2"),
    ],
)
def test_malformed_files_name_file_line_and_expectation(tmp_path, body, line, fragment):
    path = tmp_path / "bad.txt"
    path.write_text("# header\n" + body)
    with pytest.raises(MalformedFileError) as info:
        read_tum(path)
    assert info.value.line == line
    assert f"{path}, line {line}" in str(info.value)
    assert fragment in str(info.value)


def test_empty_and_missing_files(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("# only a comment\n")
    with pytest.raises(MalformedFileError, match="no data rows"):
        read_tum(path)
    with pytest.raises(FileNotFoundError, match="no such file"):
        read_tum(tmp_path / "missing.txt")


def test_read_trajectory_detects_tum_and_euroc(tmp_path):
    traj = random_trajectory(5)
    write_tum(tmp_path / "a.txt", traj)
    assert trajectory_format(tmp_path / "a.txt") == "tum"
    np.testing.assert_array_equal(read_trajectory(tmp_path / "a.txt").t_ns, traj.t_ns)
    gt_csv = EXCERPT / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    assert trajectory_format(gt_csv) == "euroc"
    assert read_trajectory(gt_csv).velocity is not None
    # 8 comma-separated columns: integer ns stamps are EuRoC pose CSV, decimal seconds are TUM.
    (tmp_path / "pose.csv").write_text("#timestamp [ns],px,py,pz,qw,qx,qy,qz\n5000000,1,2,3,1,0,0,0\n")
    assert trajectory_format(tmp_path / "pose.csv") == "euroc"
    np.testing.assert_array_equal(read_trajectory(tmp_path / "pose.csv").quat_wxyz, [[1, 0, 0, 0]])
    (tmp_path / "tum.csv").write_text("0.005,1,2,3,1,0,0,0\n")
    assert trajectory_format(tmp_path / "tum.csv") == "tum"
    np.testing.assert_array_equal(read_trajectory(tmp_path / "tum.csv").quat_wxyz, [[0, 1, 0, 0]])
    (tmp_path / "imu.csv").write_text("1403715273262142976,0,0,0,0,0,9.8\n")
    with pytest.raises(MalformedFileError, match="not a trajectory"):
        read_trajectory(tmp_path / "imu.csv")


def test_a_repeated_stamp_keeps_its_first_row_with_a_warning(tmp_path):
    """As evo reads such files (its test trajectory V102.txt has one): the rows are kept but the first of the
    repeated stamp, and the warning names file, line and the line it repeats."""
    path = tmp_path / "dup.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n2.0 9 0 0 0 0 0 1\n3.0 2 0 0 0 0 0 1\n")
    with pytest.warns(UserWarning, match=r"dup.txt:4: time stamp 2000000000 ns repeats the stamp of line 3"):
        traj = read_tum(path)
    assert traj.t_ns.tolist() == [10**9, 2 * 10**9, 3 * 10**9]
    assert traj.position[:, 0].tolist() == [0.0, 1.0, 2.0]
