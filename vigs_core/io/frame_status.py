"""``frame_status.txt``: the estimator's status of every processed frame, one ``stamp_ns status`` line each.

The status is the metric claim the estimator made for the frame (``tracking`` / ``reinitialised``: metric and
gravity-aligned; ``initialising`` / ``lost``: not; see :mod:`vigs_core.vio.odometry`). ``vigs run`` and the
frontend node write it beside ``trajectory.txt``.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from vigs_core.io.text_table import MalformedFileError, data_lines

HEADER = "# timestamp[ns] status (initialising | tracking | lost | reinitialised)\n"


def write_frame_status(path: str | Path, status: Mapping[int, str]) -> None:
    """Write ``{stamp_ns: status}`` in stamp order."""
    Path(path).write_text(HEADER + "".join(f"{t} {status[t]}\n" for t in sorted(status)))


def read_frame_status(path: str | Path) -> dict[int, str]:
    """``{stamp_ns: status}`` of a ``frame_status.txt``."""
    out = {}
    for number, text in data_lines(path):
        fields = text.split()
        if len(fields) != 2 or not fields[0].isdigit():
            raise MalformedFileError(path, number, f"expected 'stamp_ns status', got {text!r}")
        out[int(fields[0])] = fields[1]
    return out
