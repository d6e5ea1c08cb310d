"""Read a trajectory file whose format (TUM text or EuRoC CSV) is recognised from its content."""
from __future__ import annotations

import re
from pathlib import Path

from vigs_core.io.euroc import read_euroc_groundtruth
from vigs_core.io.text_table import MalformedFileError, comment_lines, data_lines, split_fields
from vigs_core.io.tum import read_tum
from vigs_core.types import Trajectory

# Integer stamps at or above this are nanoseconds (1e12 ns is 16.7 min; 1e12 s is 31,700 years).
_NS_STAMP_MIN = 10**12
_NS_HEADER = re.compile(r"\[ns\]|\(ns\)", re.IGNORECASE)


def trajectory_format(path: str | Path) -> str:
    """``"euroc"`` or ``"tum"`` for a trajectory file, from its first data line and header comments.

    EuRoC CSV: comma-separated with 17 columns (pose, velocity, biases); or 8 columns with an integer
    stamp that is either at least 1e12 or announced as ``[ns]``/``(ns)`` in a ``#`` header.
    TUM: 8 fields (whitespace or comma separated) with the stamp in seconds.
    """
    first = next(data_lines(path), None)
    if first is None:
        raise MalformedFileError(path, 0, "no data rows; expected a TUM or EuRoC CSV trajectory")
    number, text = first
    csv_fields = split_fields(text, "comma")
    if len(csv_fields) == 17:
        return "euroc"
    if len(csv_fields) == 8 and csv_fields[0].isdigit():
        if int(csv_fields[0]) >= _NS_STAMP_MIN or any(_NS_HEADER.search(c) for c in comment_lines(path)):
            return "euroc"
    if len(split_fields(text, "whitespace_or_comma")) == 8:
        return "tum"
    raise MalformedFileError(
        path,
        number,
        "not a trajectory: expected TUM 'timestamp[s] tx ty tz qx qy qz qw' or EuRoC CSV "
        f"'timestamp[ns],px,py,pz,qw,qx,qy,qz[,v,bw,ba]', found '{text[:80]}'",
    )


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM text or EuRoC CSV trajectory, recognising the format by content (:func:`trajectory_format`)."""
    if trajectory_format(path) == "euroc":
        return read_euroc_groundtruth(path)
    return read_tum(path)
