"""TUM RGB-D trajectory text: one pose per line, ``timestamp tx ty tz qx qy qz qw``.

Format (Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012): timestamp in
seconds (decimal), position in metres, Hamilton quaternion in ``(x, y, z, w)`` order; ``#`` starts a
comment line. Fields may be separated by whitespace or commas. Stamps are converted to integer
nanoseconds exactly (no float round trip) and written back with all 9 decimals.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from vigs_core.io.text_table import (
    normalized_quaternions,
    ns_to_seconds_text,
    read_stamped_rows,
    stamp_order,
)
from vigs_core.types import Trajectory

TUM_LAYOUT = "timestamp[s] tx ty tz qx qy qz qw"


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file into a :class:`Trajectory` (rows sorted by stamp).

    A repeated stamp keeps its first row, with a warning (evo reads such files too).

    Raises:
        MalformedFileError: a line without 8 fields, an unparsable number or a non-unit quaternion (the message
            names file and line).
    """
    t_ns, values, lines = read_stamped_rows(path, (8,), "whitespace_or_comma", "s", TUM_LAYOUT)
    quat_xyzw = normalized_quaternions(path, values[:, 3:7], lines)
    order = stamp_order(path, t_ns, lines, keep_first=True)
    quat_wxyz = np.concatenate((quat_xyzw[:, 3:], quat_xyzw[:, :3]), axis=1)
    return Trajectory(t_ns[order], values[order, :3], quat_wxyz[order])


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write ``trajectory`` as TUM text (header comment, stamps with 9 decimals, shortest exact floats).

    Only the poses are written; velocities and biases have no place in the format
    (use :func:`vigs_core.io.write_euroc_groundtruth` to keep them).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    quat_xyzw = np.concatenate((trajectory.quat_wxyz[:, 1:], trajectory.quat_wxyz[:, :1]), axis=1)
    with path.open("w", encoding="utf-8") as f:
        f.write(f"# {TUM_LAYOUT}\n")
        for t, p, q in zip(trajectory.t_ns, trajectory.position, quat_xyzw):
            numbers = " ".join(repr(float(v)) for v in (*p, *q))
            f.write(f"{ns_to_seconds_text(t)} {numbers}\n")
